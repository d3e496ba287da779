"""Identifying an arm through the driver: the excitation run on the arm (`driving`, with the
`policy.controllers.excitation` controller), its records (`recording`), the fit of the twin
(`fitting`, over `reach_sim_bridge.fit`), the report (`report`), the controller gap a fitted
twin closes (`twin_gap`), and the command line `tools/identify.py` runs (`cli`).
"""
