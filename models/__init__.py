"""The project's data, no code: the device spec (vrscroll/spec.toml) and the MJCF generated from it, the
evaluation shapes, the perception constants. A package only so that it installs with the code and is
found through importlib.resources (twin.paths.MODELS_DIR)."""
