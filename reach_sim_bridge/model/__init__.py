"""The Alpha 5's model, Menagerie-style: the MJCF and its README of sources, `ArmParams`, the
motor model, the MuJoCo arm, its inverse kinematics and the sensors' noise.

Controllers that need a twin import this, never the emulator.
"""
