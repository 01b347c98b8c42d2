"""Camera rigs: distributions over camera poses and intrinsics, as TOML presets (presets/*.toml)."""
