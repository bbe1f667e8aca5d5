"""The device itself: its spec (read from models/vrscroll/spec.toml, in SI), the kinematics of its
touch surface, the MJCF generated from the spec, and where device profiles live and which one is
selected (`profile`; the profile folder's reader is twin.formats.profile).

The bottom of the code's layers (README "Layout"): imports only this package, `twin.checks`,
`twin.errors` and `twin.paths`; the spec's TOML reader and writer is its own (`spec_toml`).
Everything else that needs a number about the device asks `twin.device.spec`.
"""
