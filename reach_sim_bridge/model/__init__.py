"""The Alpha 5's model, Menagerie-style: the MJCF and its README of sources, `ArmParams`, the
motor model, the MuJoCo arm, its inverse kinematics, the sensors' noise and the fitted twin's
file (`twin`: the parameters with the fit's measured delay and figures).

Controllers that need a twin import this, never the emulator.
"""
