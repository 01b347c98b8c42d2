"""The procedural city: scene descriptions as plain data, and their presets (presets/*.toml)."""
