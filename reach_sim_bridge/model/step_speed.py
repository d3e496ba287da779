"""How fast `Alpha5Arm.step` runs the way the RL environment calls it (random currents held for
`substeps` physics steps of 2 ms, 20 Hz control, episodes of 20 s), with and without fluid drag,
against the same motor law evaluated once per control period with the period run by one
``mj_step(m, d, nstep)`` call (the cost of the per-step clamp), against the rejected implicit
integrator, and against the naive alternative (motor torque computed explicitly each step in
numpy, which also chatters at the back-EMF limit). tools/bench_sim.py prints these rows.

Rates are per CPU second of this process (``process_time``: the rate on one dedicated core),
each the best of `repeats` windows, so a shared machine's load counts less.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import mujoco
import numpy as np

from protocol.alpha5 import DEFAULT_CURRENT_LIMITS_MA
from reach_sim_bridge.model.arm import Alpha5Arm, ArmParams

CONTROL_HZ = 20.0
EPISODE_S = 20.0


@dataclass
class BenchResult:
    """One measured line: a rate (per second of wall time) and extra figures."""

    name: str
    rate: float
    unit: str
    extra: dict[str, str] = field(default_factory=dict)

    def line(self) -> str:
        extras = "  ".join(f"{k}={v}" for k, v in self.extra.items())
        return f"{self.name:<46} {self.rate:>10,.0f} {self.unit:<16} {extras}"


def best_rate(run_once: Callable[[], int], seconds: float, repeats: int) -> float:
    """Best units per CPU second over `repeats` windows of seconds/repeats CPU time each;
    run_once does one chunk of work and returns how many units it did."""
    window = seconds / repeats
    best = 0.0
    for _ in range(repeats):
        done = 0
        start = time.process_time()
        while (elapsed := time.process_time() - start) < window:
            done += run_once()
        best = max(best, done / elapsed)
    return best


def _random_currents(rng: np.random.Generator, count: int) -> np.ndarray:
    limits = np.array(DEFAULT_CURRENT_LIMITS_MA)
    return rng.uniform(-1.0, 1.0, size=(count, 4)) * limits


def _label(params: ArmParams) -> str:
    return "drag" if params.fluid_drag and params.in_water else "no drag"


def bench_arm_step(
    params: ArmParams,
    seconds: float,
    repeats: int,
    substeps: int = 25,
    seed: int = 0,
    integrator: str = "Euler",
) -> BenchResult:
    """arm.step(currents, n=substeps), one 20 s episode of random currents per chunk.

    integrator "implicitfast" measures the rejected integrator (MuJoCo also differentiates
    the fluid drag each step then)."""
    arm = Alpha5Arm(params, seed=seed)
    if integrator == "implicitfast":
        arm.model.opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    commands = _random_currents(np.random.default_rng(seed), int(EPISODE_S * CONTROL_HZ))

    def episode() -> int:
        arm.reset()
        for cmd in commands:
            arm.step(cmd, n=substeps)
        return len(commands) * substeps

    rate = best_rate(episode, seconds, repeats)
    name = f"arm.step n={substeps} ({_label(params)})"
    if integrator != "Euler":
        name = f"rejected: {name[:-1]}, {integrator})"
    return BenchResult(
        name,
        rate,
        "physics steps/s",
        {"control_steps/s": f"{rate / substeps:,.0f}", "real_time_x": f"{rate * arm.dt:,.0f}"},
    )


def bench_measured_period(
    params: ArmParams,
    seconds: float,
    repeats: int,
    substeps: int = 25,
    seed: int = 0,
    single: bool = False,
) -> BenchResult:
    """A control period with its energy measured at the physics rate, as every evaluation
    steps (the env with `measure_power`, the direct backend): one `arm.step(..., n, work=w)`
    call, or (`single`, the way they stepped before) n single steps with |tau qdot| read
    after each. Both give the same sums to the bit (tests/test_arm_model.py)."""
    arm = Alpha5Arm(params, seed=seed)
    commands = _random_currents(np.random.default_rng(seed), int(EPISODE_S * CONTROL_HZ))

    def episode() -> int:
        arm.reset()
        for cmd in commands:
            work = np.zeros(4)
            if single:
                for _ in range(substeps):
                    arm.step(cmd, n=1)
                    work += np.abs(arm.tau * arm.qdot)
            else:
                arm.step(cmd, n=substeps, work=work)
        return len(commands) * substeps

    rate = best_rate(episode, seconds, repeats)
    how = f"{substeps} single steps read back" if single else f"work= in one call of n={substeps}"
    return BenchResult(
        f"energy-measured period: {how}",
        rate,
        "physics steps/s",
        {"control_steps/s": f"{rate / substeps:,.0f}"},
    )


def bench_clamp_once_per_period(
    params: ArmParams, seconds: float, repeats: int, substeps: int = 25, seed: int = 0
) -> BenchResult:
    """Baseline: the same commands and motor law, but the back-EMF regime chosen once per
    control period and the period run in C by one mj_step(m, d, nstep) call. The ratio to
    bench_arm_step is the cost of re-evaluating the clamp every physics step."""
    arm = Alpha5Arm(params, seed=seed)
    m, d = arm.model, arm.data
    motor = arm.motor
    k = motor.torque_scale * motor.torque_per_amp
    ke, r, v = motor.backemf_per_speed, motor.resistance, motor.supply_voltage
    commands = _random_currents(np.random.default_rng(seed), int(EPISODE_S * CONTROL_HZ))
    commands /= 1000.0  # A
    damping = m.dof_damping[:4]
    base = np.asarray(params.damping)

    def episode() -> int:
        arm.reset()
        for amps in commands:
            w = d.qvel[:4]
            hi = w > (v - r * amps) / ke
            lo = w < (-v - r * amps) / ke
            volt = hi | lo
            d.ctrl[:4] = np.where(volt, np.where(hi, 1.0, -1.0) * k * v / r, k * amps)
            damping[:] = np.where(volt, base + k * ke / r, base)
            mujoco.mj_step(m, d, nstep=substeps)
        return len(commands) * substeps

    rate = best_rate(episode, seconds, repeats)
    return BenchResult(
        f"baseline: clamp once per period ({_label(params)})",
        rate,
        "physics steps/s",
        {"control_steps/s": f"{rate / substeps:,.0f}", "real_time_x": f"{rate * arm.dt:,.0f}"},
    )


def bench_explicit_clamp(params: ArmParams, seconds: float, repeats: int) -> BenchResult:
    """The rejected design: MotorModel.torque() in numpy each step, applied explicitly.

    Drives all joints at their current limit from rest and reports the speed ripple once
    they are on the back-EMF line (largest standard deviation over the last 100 steps)."""
    arm = Alpha5Arm(params)
    m, d = arm.model, arm.data
    motor = arm.motor
    command = motor.current_limits_mA.copy()
    ripple = np.zeros(4)

    def run() -> int:
        nonlocal ripple
        arm.reset(q=[0.1, 0.1, 0.1, 0.1])
        speeds = np.empty((500, 4))
        for k in range(500):
            d.ctrl[:4] = motor.torque(command, d.qvel[:4])
            mujoco.mj_step(m, d)
            speeds[k] = d.qvel[:4]
        ripple = np.maximum(ripple, speeds[-100:].std(axis=0))
        return 500

    rate = best_rate(run, seconds, repeats)
    return BenchResult(
        f"rejected: explicit numpy clamp ({_label(params)})",
        rate,
        "physics steps/s",
        {"speed_ripple_rad/s(E,D,C,B)": ",".join(f"{x:.3f}" for x in ripple)},
    )


def adopted_ripple(params: ArmParams) -> np.ndarray:
    """Speed ripple of Alpha5Arm.step in the same test as bench_explicit_clamp."""
    arm = Alpha5Arm(params)
    arm.reset(q=[0.1, 0.1, 0.1, 0.1])
    speeds = np.empty((500, 4))
    for k in range(500):
        arm.step(arm.current_limits_mA.copy())
        speeds[k] = arm.qdot
    return speeds[-100:].std(axis=0)


def physics_rows(seconds: float, repeats: int, substeps: int = 25) -> list[BenchResult]:
    """Every physics row, with its ratio to the baseline or to the adopted design."""
    drag, dry = ArmParams(), ArmParams(fluid_drag=False)
    s, n, reps = seconds, substeps, repeats
    results = [
        bench_arm_step(drag, s, reps, n),
        bench_arm_step(dry, s, reps, n),
        bench_clamp_once_per_period(drag, s, reps, n),
        bench_clamp_once_per_period(dry, s, reps, n),
    ]
    # Short calls, as tools/identify.py's replay makes them (a 50 Hz tick of 10 physics
    # steps split where a command lands: about 5 steps a call): the per-call cost shows.
    short = [bench_arm_step(drag, s, reps, 5), bench_clamp_once_per_period(drag, s, reps, 5)]
    for adopted, baseline in ((results[0], results[2]), (results[1], results[3]), short):
        adopted.extra["vs_baseline"] = f"{adopted.rate / baseline.rate:.2f}x"
    results.extend(short)
    # The evaluations' energy at the physics rate: summed inside one call, against reading
    # tau and qdot back after each single step.
    measured = bench_measured_period(drag, s, reps, n)
    read_back = bench_measured_period(drag, s, reps, n, single=True)
    measured.extra["vs_single_steps"] = f"{measured.rate / read_back.rate:.2f}x"
    results += [measured, read_back]
    implicit = bench_arm_step(drag, s, reps, n, integrator="implicitfast")
    implicit.extra["vs_adopted"] = f"{implicit.rate / results[0].rate:.2f}x"
    results.append(implicit)
    # Zero gravity, in air, armature -20 % (a randomised arm): the worst case for chatter.
    light = ArmParams(
        gravity=(0.0, 0.0, 0.0), water_density=0.0, armature=(0.096, 0.096, 0.096, 0.0056)
    )
    explicit = bench_explicit_clamp(light, s, reps)
    explicit.extra["adopted_ripple"] = ",".join(f"{x:.3f}" for x in adopted_ripple(light))
    results.append(explicit)
    return results
