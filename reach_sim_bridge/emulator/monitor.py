"""The devices' "Monitor" readings: internal temperature, humidity, pressure, supply voltage.

Each axis device of a real arm reports its housing's climate (INTERNAL_HUMIDITY 0x65,
INTERNAL_TEMPERATURE 0x66, INTERNAL_PRESSURE 0x67, and FACTORY_CLIMATE 0x28: the same three
measured at assembly) and the supply voltage (VOLTAGE 0x90), and raises HARDWARE_STATUS flags
when they cross factory levels. This module is a deliberately simple model of them, stepped
with the motor currents once per physics step. Per device i, with the motor current I_i (A),
the winding resistance R_i (ohm) and the step h (s):

    temperature   tau_th dT_i/dt = T_water + R_th I_i^2 R_i - T_i        (T_i(0) = T_water)
    humidity      tau_leak dH_i/dt = 100 % - H_i   while leaking, else constant (H_factory)
    gas pressure  tau_leak dG_i/dt = P_outside - G_i  while leaking, else constant (P_factory)
    pressure      P_i = G_i (T_i + 273.15) / (T_factory + 273.15)        (ideal gas, sealed)
    bus voltage   tau_v dV/dt = V_supply - R_source (I_quiescent + sum_i |I_i|) - V

Each lag is integrated exactly over a step (x += (target - x)(1 - exp(-h / tau))), so the
result does not depend on the step. Every device reports the same bus voltage. The model
only reports: the motors keep seeing the nominal supply (the physics is not changed by it).

Flags (levels in `MonitorConfig`, each with a hysteresis so a reading at the level does not
chatter): OVER_TEMPERATURE above `over_temperature_c`, OVER_HUMIDITY above
`over_humidity_pct`, OVER_PRESSURE above `over_pressure_bar`, LOW_SUPPLY_VOLTAGE below
`low_voltage_v`. A flag is a condition: it clears when the reading is back past its level by
the hysteresis.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from protocol import HardwareStatus
from reach_sim_bridge.emulator.faults import Leak

KELVIN = 273.15

MONITOR_FLAGS = (
    HardwareStatus.OVER_TEMPERATURE
    | HardwareStatus.OVER_HUMIDITY
    | HardwareStatus.OVER_PRESSURE
    | HardwareStatus.LOW_SUPPLY_VOLTAGE
)


@dataclass(frozen=True)
class MonitorConfig:
    """Constants and factory levels of the monitor model (choices, documented in
    docs/protocol.md section 3a; the vendor does not publish its levels)."""

    # FACTORY_CLIMATE: what the housing held when it was sealed.
    factory_temperature_c: float = 20.0
    factory_pressure_bar: float = 1.0
    factory_humidity_pct: float = 10.0
    # Heat: housing-to-water thermal resistance and time constant.
    thermal_resistance_k_per_w: float = 10.0
    thermal_time_constant_s: float = 120.0
    # Supply: tether and supply source resistance, the electronics' own draw, a filter.
    source_resistance_ohm: float = 1.0
    quiescent_current_a: float = 0.1
    voltage_time_constant_s: float = 0.05
    # Factory levels and hysteresis.
    over_temperature_c: float = 60.0
    temperature_hysteresis_c: float = 5.0
    over_humidity_pct: float = 40.0
    humidity_hysteresis_pct: float = 5.0
    over_pressure_bar: float = 1.3
    pressure_hysteresis_bar: float = 0.05
    low_voltage_v: float = 18.0
    voltage_hysteresis_v: float = 0.5

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if not math.isfinite(value):
                raise ValueError(f"monitor {name} must be finite, got {value}")
        for name in (
            "thermal_time_constant_s",
            "voltage_time_constant_s",
            "factory_pressure_bar",
        ):
            if getattr(self, name) <= 0.0:
                raise ValueError(f"monitor {name} must be > 0, got {getattr(self, name)}")
        for name in (
            "thermal_resistance_k_per_w",
            "source_resistance_ohm",
            "quiescent_current_a",
            "temperature_hysteresis_c",
            "humidity_hysteresis_pct",
            "pressure_hysteresis_bar",
            "voltage_hysteresis_v",
        ):
            if getattr(self, name) < 0.0:
                raise ValueError(f"monitor {name} must be >= 0, got {getattr(self, name)}")

    @property
    def factory_climate(self) -> tuple[float, float, float]:
        """The FACTORY_CLIMATE payload: [temperature degC, pressure bar, humidity %]."""
        return (self.factory_temperature_c, self.factory_pressure_bar, self.factory_humidity_pct)


class Monitor:
    """The readings of n devices, stepped with their motor currents."""

    def __init__(
        self,
        config: MonitorConfig,
        resistances_ohm: Sequence[float],
        water_temperature_c: float,
        supply_v: float,
        humidity_pct: float | None = None,
    ) -> None:
        self.config = config
        self._r = [float(r) for r in resistances_ohm]
        n = len(self._r)
        self.water_temperature_c = float(water_temperature_c)
        self.temperature_c = [self.water_temperature_c] * n
        h0 = config.factory_humidity_pct if humidity_pct is None else float(humidity_pct)
        self.humidity_pct = [h0] * n
        self._gas_bar = [config.factory_pressure_bar] * n
        self.voltage_v = supply_v - config.source_resistance_ohm * config.quiescent_current_a
        self.flags = [HardwareStatus.NONE] * n
        self._state = [0] * n  # the flags as plain ints
        self._low = False
        self.leaks: list[Leak | None] = [None] * n
        self._h = -1.0
        self._a_th = self._a_v = 0.0
        self._a_leak: list[float] = [0.0] * n
        self._update_flags()

    def pressure_bar(self, i: int) -> float:
        """Internal pressure of device i (bar): the gas at the housing's temperature."""
        t0 = self.config.factory_temperature_c + KELVIN
        return self._gas_bar[i] * (self.temperature_c[i] + KELVIN) / t0

    def leak(self, i: int, leak: Leak | None) -> None:
        """Start (or, with None, stop) a leak into device i's housing."""
        self.leaks[i] = leak
        self._h = -1.0  # recompute the step factors

    def step(self, h: float, currents_a: Sequence[float], supply_v: float) -> None:
        """Advance h seconds with the motor currents (A, one per device) held."""
        cfg = self.config
        if h != self._h:
            self._h = h
            self._a_th = -math.expm1(-h / cfg.thermal_time_constant_s)
            self._a_v = -math.expm1(-h / cfg.voltage_time_constant_s)
            self._a_leak = [
                0.0 if lk is None else -math.expm1(-h / lk.time_constant_s) for lk in self.leaks
            ]
        rth = cfg.thermal_resistance_k_per_w
        water = self.water_temperature_c
        a_th = self._a_th
        temps = self.temperature_c
        total = cfg.quiescent_current_a
        for i, amps in enumerate(currents_a):
            heat = amps * amps * self._r[i]
            temps[i] += (water + rth * heat - temps[i]) * a_th
            total += abs(amps)
            lk = self.leaks[i]
            if lk is not None:
                a = self._a_leak[i]
                self.humidity_pct[i] += (100.0 - self.humidity_pct[i]) * a
                self._gas_bar[i] += (lk.outside_pressure_bar - self._gas_bar[i]) * a
        target_v = supply_v - cfg.source_resistance_ohm * total
        self.voltage_v += (target_v - self.voltage_v) * self._a_v
        self._update_flags()

    def _update_flags(self) -> None:
        # Plain floats and ints: this runs every 10 ms of sim time for every device.
        cfg = self.config
        self._low = _hysteresis(
            self._low,
            self.voltage_v < cfg.low_voltage_v,
            cfg.low_voltage_v + cfg.voltage_hysteresis_v < self.voltage_v,
        )
        low_bit = _LOW if self._low else 0
        t_on, t_off = cfg.over_temperature_c, cfg.over_temperature_c - cfg.temperature_hysteresis_c
        h_on, h_off = cfg.over_humidity_pct, cfg.over_humidity_pct - cfg.humidity_hysteresis_pct
        p_on, p_off = cfg.over_pressure_bar, cfg.over_pressure_bar - cfg.pressure_hysteresis_bar
        for i, state in enumerate(self._state):
            t, hum, p = self.temperature_c[i], self.humidity_pct[i], self.pressure_bar(i)
            hot = _hysteresis(state & _HOT != 0, t > t_on, t < t_off)
            wet = _hysteresis(state & _WET != 0, hum > h_on, hum < h_off)
            high = _hysteresis(state & _HIGH != 0, p > p_on, p < p_off)
            bits = (_HOT if hot else 0) | (_WET if wet else 0) | (_HIGH if high else 0) | low_bit
            if bits != state:
                self._state[i] = bits
                self.flags[i] = HardwareStatus(bits)


_HOT = int(HardwareStatus.OVER_TEMPERATURE)
_WET = int(HardwareStatus.OVER_HUMIDITY)
_HIGH = int(HardwareStatus.OVER_PRESSURE)
_LOW = int(HardwareStatus.LOW_SUPPLY_VOLTAGE)


def _hysteresis(now: bool, above: bool, clear: bool) -> bool:
    """The flag's next state: set past the level, cleared past the level and the band."""
    return True if above else (False if clear else now)
