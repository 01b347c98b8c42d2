"""The procedural city: scene descriptions as plain data, and their presets (presets/*.toml).

Entry points: `omnigen.scenes.generate.SceneGenerator` (the static city once, a Scene per frame),
`omnigen.scenes.blender_backend.BlenderScene` (the only bpy importer in omnigen) and
`omnigen.scenes.raster_backend.RasterScene` (pyrender on headless EGL). See docs/scenes.md.
Importing this package imports neither bpy nor OpenGL.
"""
