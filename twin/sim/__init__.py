"""The simulated device: the twin and the batch twin (the MuJoCo plant with the firmware in the
loop at the firmware rate), step-response metrics, and the gate that checks a move before it
reaches hardware.

May import `twin.device` and `controllers`; never the link, the HIL runs or the approximation.
"""
