"""Records: the typed values that cross the layers, in SI (m, rad, s, A, N*m), data without behaviour beyond
their own arithmetic. One record per concept, shared by every layer that holds one:

    approximation.Approximation   a MorphPatch (or CBS) pose: root pose, hinge angles, flap widths, its measures
    trace.Trace                   a recording at the firmware rate, twin's and device's alike
    move_report.MoveReport        a move's step response per hinge
    calibration.Calibration       a profile's calibration: the runs and an Estimate per parameter (and per hinge)
    profile.Profile               a device profile: spec, sources, gains, mount, calibration, per-hinge plants, holding
    gains.Gains                   a gains file: one PID gain set per hinge and what they were made for
    ranges.Ranges                 the plants a device may be: each plant parameter's interval, per hinge too
    pen.PenSamples                a pen file's samples: the pen tip's positions and orientations, the device's poses
    report.Report                 a command's result: its --json document and its report's lines

The bottom of the code's layers, below `twin.device` (README "Layout"): imports neither the device nor
anything above it (the device's plant variation makes and takes `Ranges`), so `twin.formats` reads and writes
these and every layer above takes them whole (no dict of their fields crosses a layer). Units in the field
comments; degrees and millimetres only where a format writes them (twin.formats).
"""
