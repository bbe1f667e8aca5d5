"""The device itself: its spec (read from models/vrscroll/spec.toml, in SI), the kinematics of its
touch surface, the MJCF generated from the spec, and where device profiles live and which one is
selected (`profile`; the profile folder's reader is twin.formats.profile).

The bottom layer: imports nothing from the project but this package and the spec TOML's
reader and writer (`twin.formats.spec_toml`, which imports only `twin.formats.common`).
Everything else that needs a number about the device asks `twin.device.spec`.
"""
