"""Running and judging the paper's experiments: one episode (`episode`, its Diagram
`episode_diagram`), the experiments as data (`experiments`), Monte Carlo runs (`montecarlo`,
`trial_plan`, `trial_worker`, `run_folder`, `replay`) and their records (`records`), reports
(`report`, `pictures`, `graphviz`), the grasp physics lab (`lab`, `labelcheck`, `tolerance`)
and the controller across a process boundary (`bridge`, `bridge_protocol`, `bridge_station`).

Floor 10: imports `learning` and the floors below.
"""
