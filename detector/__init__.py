"""The bundled keypoint detector and its heads, which validate the data."""
