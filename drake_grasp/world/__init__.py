"""The simulated world: scenes sampled and settled by physics (`scene`) on the table and
its sheet (`table`), and the station - UR5, 2F-85, wrist depth cameras, table, objects -
built as a Drake Diagram (`station`).

Floor 7: imports `systems` and the floors below.
"""
