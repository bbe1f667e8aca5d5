"""The evaluation: seeded approach starts, the CBS baseline in MuJoCo with the target as collision
geometry (its convex decomposition), and the paper's Table 1 run over methods, shapes and starts,
one writer per output folder (a lock).

May import `twin.device`, `twin.sim` and `twin.morphpatch`.
"""
