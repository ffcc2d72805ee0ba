"""What every benchmark shares: paths, the machine description, measured child processes, the
generated KITTI-00 LiDAR sequence, the reference systems and checkouts of an earlier revision.

One implementation each; ``benchmarks/bench_*.py`` import from here instead of copying.
"""
