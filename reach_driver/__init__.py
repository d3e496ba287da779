"""Driver for the Reach Alpha 5 over serial, UDP or a CAN tunnel (see docs/architecture.md).

from reach_driver import open_transport, ArmClient
with ArmClient(open_transport("/dev/ttyUSB0")) as arm:   # start()s and close()s
    print(arm.state.q)
"""

from protocol.alpha5 import JAW, JOINTS
from reach_driver.chatter import ChatterConfig, HoldMode
from reach_driver.client import ArmClient
from reach_driver.control import ControlLoop, Pacing
from reach_driver.controllers import (
    Controller,
    ControllerInfo,
    ControllerKind,
    ControlState,
    available_controllers,
    describe_controllers,
    engineered,
    learned,
    load_controller,
)
from reach_driver.errors import (
    ArmFaultError,
    ArmIdentityError,
    ArmModelError,
    BadReadingError,
    BadUrlError,
    ControllerError,
    DriverError,
    GarbageError,
    Interrupted,
    LimitError,
    LinkDownError,
    NoResponseError,
    PortBusyError,
    PortNotFoundError,
    PortPermissionError,
    RealtimeRefusedError,
    RequestTimeoutError,
    StreamRateError,
    TransportError,
    WatchdogTrippedError,
)
from reach_driver.identity import ModelCheck
from reach_driver.interfaces import open_transport
from reach_driver.link import ClientEvent, ClientStats, EventKind, LinkConfig, LinkState
from reach_driver.listeners import PacketQueue, Subscription
from reach_driver.realtime import RealtimePolicy, RealtimeReport, RealtimeThreads
from reach_driver.records import ControlSummary, LoopTrace, StepRecord, TimingStats
from reach_driver.safety import LimitKind, SafetyConfig, SafetyGuard
from reach_driver.state import ArmState, JointState, Reading
from reach_driver.transport import Transport, TransportStats

__all__ = [
    "JAW",
    "JOINTS",
    "ArmClient",
    "ChatterConfig",
    "HoldMode",
    "ArmFaultError",
    "ArmIdentityError",
    "ArmModelError",
    "ArmState",
    "BadReadingError",
    "StreamRateError",
    "BadUrlError",
    "ClientEvent",
    "ClientStats",
    "ControlLoop",
    "ControlState",
    "ControlSummary",
    "Controller",
    "ControllerInfo",
    "ControllerKind",
    "ControllerError",
    "DriverError",
    "EventKind",
    "GarbageError",
    "Interrupted",
    "JointState",
    "LimitError",
    "LimitKind",
    "LinkConfig",
    "LinkDownError",
    "LinkState",
    "ModelCheck",
    "LoopTrace",
    "NoResponseError",
    "Pacing",
    "PacketQueue",
    "PortNotFoundError",
    "PortBusyError",
    "PortPermissionError",
    "Reading",
    "RealtimePolicy",
    "RealtimeRefusedError",
    "RealtimeReport",
    "RealtimeThreads",
    "RequestTimeoutError",
    "SafetyConfig",
    "SafetyGuard",
    "StepRecord",
    "Subscription",
    "TimingStats",
    "Transport",
    "TransportError",
    "TransportStats",
    "WatchdogTrippedError",
    "available_controllers",
    "describe_controllers",
    "engineered",
    "learned",
    "load_controller",
    "open_transport",
]
