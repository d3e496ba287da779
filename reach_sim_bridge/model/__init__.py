"""The Alpha 5's model, Menagerie-style: the MJCF and its README of sources, `ArmParams`, the
motor model, the MuJoCo arm, its inverse kinematics, the sensors' noise and the fitted twin's
file (`twin`: the parameters with the fit's measured delay and figures). Beside it, the
Reach Bravo 7's twin: `bravo7.xml`, its page of sources `bravo7.md` and `bravo7` (loading).

Controllers that need a twin import this, never the emulator.
"""
