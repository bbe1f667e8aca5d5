"""File formats: one module per format, each with one reader that validates and one writer
(docs/formats.md documents them all, with columns, keys and units).

Readers refuse bad input with a ValueError naming the file, the line or key and the reason.
Sits low: `spec_toml` and `common` import nothing else from the project (twin.device.spec reads
the spec through `spec_toml`); the other modules may import `twin.device`, `controllers` and
`twin.link.protocol` (for the firmware's gain bounds), and are imported by the packages above.
"""
