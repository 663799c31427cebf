"""The `drake-grasp` command line (`main`) and the benchmarks (`bench`).

Floor 11, the top with `drake_grasp.api`: may import every floor.
"""
