"""PID tuning on the twin: robust per-hinge gains from many simulations in parallel.

It sits above `twin.sim` (it runs the batch twin), which is why it is not under `controllers/`:
`controllers` holds what runs on the device and is imported by the simulation.
"""
