"""File formats: one module per format, each with one reader that validates and one writer
(docs/formats.md documents them all, with columns, keys and units).

Readers refuse bad input with a ValueError naming the file, the line or key and the reason (the
shared checks are twin.checks). Where a record exists (twin.records: the approximation, the trace, the move
report) a reader returns it and a writer takes it, never a dict of its fields. Above `twin.device` and
`controllers`, whose values they check, and `twin.records`;
below everything that reads or writes a file. The spec's own TOML is twin.device.spec_toml.
"""
