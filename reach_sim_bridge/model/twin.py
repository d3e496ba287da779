"""A fitted twin: an arm's parameters together with what the fit that found them measured.

An identification (`tools/identify.py`) writes a `--params` file whose ``_fit`` key holds the
fit's metadata: the transport delay it measured, each fitted parameter with its 1-sigma
uncertainty, how well the twin predicts the motions. `load_arm_params` reads such a file as
a plain `ArmParams` (it ignores keys starting with ``_``); whoever needs the metadata (the
delay is the `lambda` controller's latency) reads it as a `FittedTwin` with `read_twin`, and
`write_twin` writes one. `FittedTwin.from_json_dict` reads the same object from a dict, so a
twin handed over as a dict keeps its fit.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from protocol.models import ALPHA5, ArmModel
from reach_sim_bridge.model.params import (
    ArmParams,
    ParamsFileError,
    read_params_json,
    save_arm_params,
)

FIT_KEY = "_fit"
"""The key of a parameter file that holds `FitMetadata`."""

#: Per motions ("fit/E", "validate/C"...), per replay ("window", "open_loop"), the figures of
#: `reach_sim_bridge.fit.replay.Quality.as_dict` (r2, rms_mrad, r2_velocity...).
QualityTable = dict[str, dict[str, dict[str, float]]]


@dataclass(frozen=True)
class Estimate:
    """One fitted value and its 1-sigma uncertainty."""

    value: float
    sigma: float


@dataclass(frozen=True)
class Combination:
    """A product or ratio of parameters the data fix (e.g. "frictionloss[E]/torque_scale[E]",
    the friction in N m the drive would need at its full torque) and its 1-sigma."""

    name: str
    value: float
    sigma: float


@dataclass(frozen=True)
class Unidentified:
    """A parameter the data cannot fix: the value the twin has for it (`twin_value`, what an
    assumption made it, said in `reason`) and the combination the data do fix (None where
    there is none to give: a torque scale itself)."""

    twin_value: float
    reason: str
    known: Combination | None = None

    def to_json_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"twin_value": self.twin_value, "reason": self.reason}
        if self.known is not None:
            k = self.known
            out["known"] = {"name": k.name, "value": k.value, "sigma": k.sigma}
        return out


@dataclass(frozen=True)
class FitMetadata:
    """What an identification found beside the parameters (the file's ``_fit``). Every field
    is optional so that files with part of it (older or hand-written) still load."""

    method: str = ""
    #: what was identified: per parameter ("armature[E]", "torque_scale[D]"...) its estimate
    parameters: dict[str, Estimate] = field(default_factory=dict)
    #: what the data cannot fix, per parameter: the twin's value and the combination known
    unidentifiable: dict[str, Unidentified] = field(default_factory=dict)
    #: per joint letter, its torque scale's verdict (`reach_sim_bridge.fit.identifiability`)
    torque_scales: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: per joint letter, the directions of its fit's Fisher information and their 1-sigma
    identifiability: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: the transport delay measured (s): the median of the delays the replay used
    delay_s: float | None = None
    delay_note: str = ""
    command_step_s: float | None = None  # the arm's command step the fit chose (s)
    delay_offsets_ms: dict[str, float] = field(default_factory=dict)  # per segment
    quality_fitted: QualityTable = field(default_factory=dict)
    quality_nominal: QualityTable = field(default_factory=dict)
    sigma_note: str = ""
    arm_seconds: float | None = None  # arm time of the excitation and its moves
    log: str | None = None  # the excitation's log the fit read
    fit_seconds: float | None = None
    controller_gap: list[dict[str, Any]] | None = None  # `--check-controller`'s summary
    other: dict[str, Any] = field(default_factory=dict)  # keys not known here, kept as they are

    def __post_init__(self) -> None:
        if self.delay_s is not None and not (math.isfinite(self.delay_s) and self.delay_s >= 0):
            raise ValueError(f"delay_s must be a finite number >= 0, got {self.delay_s!r}")

    def window_rms_mrad(self, motions: str, twin: str = "fitted") -> float | None:
        """The replay's RMS over windows on `motions` ("validate/D"...) through the fitted or
        the nominal twin (mrad); None where the metadata has none."""
        table = self.quality_fitted if twin == "fitted" else self.quality_nominal
        window = table.get(motions, {}).get("window")
        return None if window is None else window["rms_mrad"]

    def to_json_dict(self) -> dict[str, Any]:
        """The ``_fit`` object (the keys in the order identification files have them)."""
        out: dict[str, Any] = {
            "method": self.method,
            "parameters": {
                k: {"value": e.value, "sigma": e.sigma} for k, e in self.parameters.items()
            },
            "delay_s": self.delay_s,
            "delay_note": self.delay_note,
            "command_step_s": self.command_step_s,
            "delay_offsets_ms": dict(self.delay_offsets_ms),
            "quality_fitted": self.quality_fitted,
            "quality_nominal": self.quality_nominal,
            "sigma_note": self.sigma_note,
            "arm_seconds": self.arm_seconds,
            "log": self.log,
            "fit_seconds": self.fit_seconds,
        }
        # after the parameters, where there are any (an older file writes back as it was)
        verdicts = {
            "unidentifiable": {k: u.to_json_dict() for k, u in self.unidentifiable.items()},
            "torque_scales": self.torque_scales,
            "identifiability": self.identifiability,
        }
        if any(verdicts.values()):
            keys = list(out)
            at = keys.index("parameters") + 1
            out = {k: out[k] for k in keys[:at]} | verdicts | {k: out[k] for k in keys[at:]}
        if self.controller_gap is not None:
            out["controller_gap"] = self.controller_gap
        out.update(self.other)
        return out

    @classmethod
    def from_json_dict(cls, data: Any, where: str = FIT_KEY) -> FitMetadata:
        """The metadata a ``_fit`` object holds (`ParamsFileError` naming the key if a value
        has the wrong type)."""
        if not isinstance(data, Mapping):
            raise ParamsFileError(f"{where} must be an object, got {type(data).__name__}")
        known = {
            "method",
            "parameters",
            "unidentifiable",
            "torque_scales",
            "identifiability",
            "delay_s",
            "delay_note",
            "command_step_s",
            "delay_offsets_ms",
            "quality_fitted",
            "quality_nominal",
            "sigma_note",
            "arm_seconds",
            "log",
            "fit_seconds",
            "controller_gap",
        }
        parameters = {}
        for name, raw in _mapping(data.get("parameters", {}), f"{where}.parameters").items():
            entry = _mapping(raw, f"{where}.parameters.{name}")
            parameters[str(name)] = Estimate(
                _number(entry.get("value"), f"{where}.parameters.{name}.value"),
                _number(entry.get("sigma"), f"{where}.parameters.{name}.sigma"),
            )
        unidentifiable = {
            str(name): _unidentified(raw, f"{where}.unidentifiable.{name}")
            for name, raw in _mapping(
                data.get("unidentifiable", {}), f"{where}.unidentifiable"
            ).items()
        }
        gap = data.get("controller_gap")
        if gap is not None and not (
            isinstance(gap, list) and all(isinstance(g, Mapping) for g in gap)
        ):
            raise ParamsFileError(f"{where}.controller_gap must be a list of objects")
        try:
            return cls(
                method=_text(data.get("method", ""), f"{where}.method"),
                parameters=parameters,
                unidentifiable=unidentifiable,
                torque_scales={
                    str(k): dict(_mapping(v, f"{where}.torque_scales.{k}"))
                    for k, v in _mapping(
                        data.get("torque_scales", {}), f"{where}.torque_scales"
                    ).items()
                },
                identifiability={
                    str(k): dict(_mapping(v, f"{where}.identifiability.{k}"))
                    for k, v in _mapping(
                        data.get("identifiability", {}), f"{where}.identifiability"
                    ).items()
                },
                delay_s=_optional_number(data.get("delay_s"), f"{where}.delay_s"),
                delay_note=_text(data.get("delay_note", ""), f"{where}.delay_note"),
                command_step_s=_optional_number(
                    data.get("command_step_s"), f"{where}.command_step_s"
                ),
                delay_offsets_ms={
                    str(k): _number(v, f"{where}.delay_offsets_ms.{k}")
                    for k, v in _mapping(
                        data.get("delay_offsets_ms", {}), f"{where}.delay_offsets_ms"
                    ).items()
                },
                quality_fitted=_quality(data.get("quality_fitted", {}), f"{where}.quality_fitted"),
                quality_nominal=_quality(
                    data.get("quality_nominal", {}), f"{where}.quality_nominal"
                ),
                sigma_note=_text(data.get("sigma_note", ""), f"{where}.sigma_note"),
                arm_seconds=_optional_number(data.get("arm_seconds"), f"{where}.arm_seconds"),
                log=None if data.get("log") is None else _text(data["log"], f"{where}.log"),
                fit_seconds=_optional_number(data.get("fit_seconds"), f"{where}.fit_seconds"),
                controller_gap=None if gap is None else [dict(g) for g in gap],
                other={k: v for k, v in data.items() if k not in known},
            )
        except ValueError as exc:
            raise ParamsFileError(f"{where}: {exc}") from exc


@dataclass(frozen=True)
class FittedTwin:
    """An arm's parameters, the fit that found them (None: not fitted, e.g. the nominal arm)
    and the file's other metadata keys (``_envelope``, ``_comment``...), kept as they are."""

    params: ArmParams = field(default_factory=ArmParams)
    fit: FitMetadata | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for key in self.metadata:
            if not key.startswith("_") or key == FIT_KEY:
                raise ValueError(
                    f"metadata keys start with '_' and {FIT_KEY} is the fit's, got {key!r}"
                )

    @property
    def delay_s(self) -> float | None:
        """The transport delay the fit measured (s), None without one."""
        return None if self.fit is None else self.fit.delay_s

    def to_json_dict(self) -> dict[str, Any]:
        """The `--params` object: every `ArmParams` field, the metadata, then ``_fit``."""
        data = self.params.to_json_dict()
        data.update(self.metadata)
        if self.fit is not None:
            data[FIT_KEY] = self.fit.to_json_dict()
        return data

    @classmethod
    def from_json_dict(
        cls,
        data: Any,
        where: str = "params",
        model: ArmModel = ALPHA5,
        nominal: ArmParams | None = None,
    ) -> FittedTwin:
        """The twin of `model` a `--params` object describes (`ArmParams.from_json_dict`'s
        rules, the rest `nominal`, and ``_fit`` read as `FitMetadata`)."""
        params = ArmParams.from_json_dict(data, where, model, nominal)
        fit = data.get(FIT_KEY)
        return cls(
            params,
            None if fit is None else FitMetadata.from_json_dict(fit, f"{where}: {FIT_KEY}"),
            {k: v for k, v in data.items() if k.startswith("_") and k != FIT_KEY},
        )


def read_twin(
    path: str | Path, model: ArmModel = ALPHA5, nominal: ArmParams | None = None
) -> FittedTwin:
    """The fitted twin of `model` a parameter file holds (a file without ``_fit`` gives
    ``fit=None``; what it does not name is `nominal`)."""
    return FittedTwin.from_json_dict(read_params_json(path), str(path), model, nominal)


def write_twin(twin: FittedTwin, path: str | Path) -> Path:
    """Write `twin` as a `--params` file that `load_arm_params` and `read_twin` both read."""
    extra = dict(twin.metadata)
    if twin.fit is not None:
        extra[FIT_KEY] = twin.fit.to_json_dict()
    return save_arm_params(twin.params, path, extra=extra)


def _mapping(raw: Any, what: str) -> Mapping[str, Any]:
    if not isinstance(raw, Mapping):
        raise ParamsFileError(f"{what} must be an object, got {type(raw).__name__}")
    return raw


def _number(raw: Any, what: str) -> float:
    if isinstance(raw, bool) or not isinstance(raw, (int, float)):
        raise ParamsFileError(f"{what} must be a number, got {raw!r}")
    return float(raw)


def _unidentified(raw: Any, what: str) -> Unidentified:
    entry = _mapping(raw, what)
    known = entry.get("known")
    combination = None
    if known is not None:
        k = _mapping(known, f"{what}.known")
        combination = Combination(
            _text(k.get("name"), f"{what}.known.name"),
            _number(k.get("value"), f"{what}.known.value"),
            _number(k.get("sigma"), f"{what}.known.sigma"),
        )
    return Unidentified(
        _number(entry.get("twin_value"), f"{what}.twin_value"),
        _text(entry.get("reason", ""), f"{what}.reason"),
        combination,
    )


def _optional_number(raw: Any, what: str) -> float | None:
    return None if raw is None else _number(raw, what)


def _text(raw: Any, what: str) -> str:
    if not isinstance(raw, str):
        raise ParamsFileError(f"{what} must be a string, got {raw!r}")
    return raw


def _quality(raw: Any, what: str) -> QualityTable:
    out: QualityTable = {}
    for motions, replays in _mapping(raw, what).items():
        out[str(motions)] = {
            str(replay): {
                str(k): v if isinstance(v, int) and not isinstance(v, bool) else _number(v, what)
                for k, v in _mapping(figures, f"{what}.{motions}.{replay}").items()
            }
            for replay, figures in _mapping(replays, f"{what}.{motions}").items()
        }
    return out
