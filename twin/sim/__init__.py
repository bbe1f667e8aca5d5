"""The simulated device: the twin and the batch twin (the MuJoCo plant with the firmware in the
loop at the firmware rate), step-response metrics, the gate that checks a move before it
reaches hardware, and the replay of timed targets on the twin.

May import `twin.device`, `twin.records`, `twin.formats` and `controllers`; never the link, the HIL runs or the
approximation.
"""
