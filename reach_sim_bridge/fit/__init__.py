"""System identification of the Alpha 5 twin by simulation (docs/identification.md).

The data are current-mode motions of one joint at a time (`Segment`: the states a control loop
saw on its tick grid and the currents it held over each period, as `reach_driver`'s
`LoopTrace` gives them). The twin is `Alpha5Arm`, the model the controllers use. A
parameter set is scored by replaying the logged commands open loop through MuJoCo:

- multiple shooting: each segment is cut into windows of `window_s`; each window starts
  from the measured state (the excited joint's corrected by fitted nuisances,
  `Segment.start_fix`, where the fit has them), so a rollout cannot drift further than one
  window;
- the joints not being excited are held on their measured path (their position and
  velocity are set to the logged values at every tick), so one joint's fit does not
  depend on the others' parameters beyond what the pose makes them load it with;
- the link's transport delay: command row i (sent at tick i-1) lands at t[i-1] plus its
  delay, measured per command from the driver's timestamps (`link_delays`, the segment's
  `link_delay_s`) plus a constant per segment (`offset_s`, `tune_offsets`), on the arm's
  own step grid (`Replay.quantum_s`), and is held until the next lands;
- windows are cut where the link stalled (`Replay.windows`).

`fit_arm` fits each joint by Levenberg-Marquardt with forward-difference Jacobians over
log-parameters (armature, viscous damping, Coulomb friction of the joint, and a link mass for
the net gravity-buoyancy load where there is one) with the delays held fixed: fitted beside
the armature, one constant delay traded off against it (both delay the response to a current
step by a fraction of a tick). Each value gets an uncertainty from the Jacobian at the
optimum, sqrt(diag(sigma^2 (J^T J)^-1)). `fit_joint` can still fit a constant delay
(`DELAY`) where there are no timestamps. Numpy only.

Modules: `segments` (the logged data, measured delays, the .npz log), `replay` (scoring a
parameter set), `joint_fit` (one joint), `arm_fit` (the whole arm, delay offsets).
"""
