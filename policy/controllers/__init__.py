"""Controllers the `reach_stack.controllers` entry points name, each with its observation and
weights, and the excitation an identification drives the arm with (`excitation`).

They depend on the driver's `Controller` interface and, where they need a twin of the arm, on
`reach_sim_bridge.model`; never on the emulator, the training code or the campaigns.
"""
