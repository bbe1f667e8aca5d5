"""The evaluation: seeded approach starts, the CBS baseline in MuJoCo with the target as collision
geometry (its convex decomposition), the paper's Table 1 run over methods, shapes and starts, design
sweeps (designs x shapes x starts x methods x plants), one writer per output folder (a lock), and the
backends their tasks run on (local processes, Ray).

May import `twin.device`, `twin.sim` and `twin.morphpatch`.
"""
