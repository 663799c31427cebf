"""The `drake-grasp` command line: `main` assembles the parser from one module per command
group (`run`, `learn`, `gpd`, `experiments`, `lab`, `tools`; shared argument types in
`args`), and the benchmarks (`bench`).

Floor 11, the top with `drake_grasp.api`: may import every floor.
"""
