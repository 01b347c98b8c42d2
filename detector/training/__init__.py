"""The recipe, the loss and its assigner, one step, the run (detector then crop phase)."""
