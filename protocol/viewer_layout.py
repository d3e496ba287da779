"""What the driver's and the simulator's recordings show alike in a Rerun viewer: a 3D eye that
frames every pose the arm can take, plots that span the recording's whole time axis without
legends over their data, and a live time panel that follows the newest data.

It sits in `protocol` beside `protocol.viewer`, for the same reason: both recorders use it and
neither may import the other. Each recorder describes its own drawn arm (`ArmBody`: the
driver's from its kinematic chain, the simulator's from its MuJoCo model); the bound on the
arm's reach and the eye placed from it are computed here, once.

Why each is set rather than left to the viewer (rerun 0.41):

- the default 3D eye frames the bounding box of what is drawn at the first frame, from 1.5
  times its half diagonal: a 55 degree view of that cuts off what lies near the box's corners,
  and an arm that then reaches up leaves the view (the top link and the jaws);
- a plot's default time range is the span of its own data: the diagnostics, read once at
  the start of a run, span a single instant, which the plot widens to +-1 ns and labels
  "-0.000001 ms";
- a legend sits on the plot's data, and in the small plots it covers much of it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import rerun.blueprint as rrb
from rerun import encodings

Vec3 = tuple[float, float, float]

#: Series colours, one per device in E D C B then the jaws (A): the plots of one value per
#: device (errors, torques, velocities, diagnostics) colour them alike.
JOINT_COLORS: tuple[tuple[int, int, int, int], ...] = (
    (230, 90, 60, 255),  # E red
    (90, 180, 80, 255),  # D green
    (70, 130, 230, 255),  # C blue
    (200, 170, 40, 255),  # B yellow
)
JAW_COLOR = (150, 150, 150, 255)  # A grey
#: The arm as reported (and q in a position plot), and the target (its ghost, its line).
ARM_COLOR = (230, 150, 40, 255)
TARGET_COLOR = (80, 170, 255, 255)
#: How the colour key reads in a view's title.
JOINT_KEY = "E red, D green, C blue, B yellow"

#: The vertical field of view of rerun's 3D eye (0.41 has no setting for it).
EYE_FOV_Y_RAD = math.radians(55.0)
#: The narrowest 3D view (width / height) the whole reach must still fit in: the blueprints'
#: 3D view in a 4:3 window or any wider one (a wider view shows more around it).
MIN_VIEW_ASPECT = 0.8
#: Room left around the reach, as a fraction of the eye's distance.
EYE_MARGIN = 0.05
#: From where the eye looks at the arm: rerun's own default direction (from -y, a little to
#: the right and above), so the arm's zero pose, in the x-z plane, is seen side on.
EYE_DIRECTION: Vec3 = (0.25, 0.75, -0.25)
WORLD_UP: Vec3 = (0.0, 0.0, 1.0)


@dataclass(frozen=True)
class Ball:
    """A ball enclosing a drawn geom (or part of one), in world coordinates."""

    center: Vec3
    radius: float


@dataclass(frozen=True)
class ArmBody:
    """One rigid body of a drawn arm at any one pose, in world coordinates: the revolute joint
    that turns it against its parent (a point on its axis, and the axis) and balls that enclose
    its geoms. A body fixed to its parent, or to the world, has no joint (pivot None); one on a
    slide joint is given as fixed with its balls grown by the slide's travel."""

    parent: int | None  # the index of the body it hangs from; None: fixed to the world
    pivot: Vec3 | None
    axis: Vec3 | None
    balls: tuple[Ball, ...]


@dataclass(frozen=True)
class Reach:
    """A ball holding every point of the arm at every pose its joints allow (at any angle)."""

    center: Vec3
    radius: float


def _sub(a: Sequence[float], b: Sequence[float]) -> Vec3:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _dot(a: Sequence[float], b: Sequence[float]) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a: Sequence[float], b: Sequence[float]) -> Vec3:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _norm(a: Sequence[float]) -> float:
    return math.sqrt(_dot(a, a))


def _unit(a: Sequence[float]) -> Vec3:
    n = _norm(a)
    return (a[0] / n, a[1] / n, a[2] / n)


def _nearest_on_axis(point: Vec3, pivot: Vec3, axis: Vec3) -> Vec3:
    u = _unit(axis)
    s = _dot(_sub(point, pivot), u)
    return (pivot[0] + s * u[0], pivot[1] + s * u[1], pivot[2] + s * u[2])


def reach(bodies: Sequence[ArmBody]) -> Reach:
    """The ball the arm can never leave, centred on the base joint's axis level with the next
    joint (the shoulder).

    Its radius bounds the distance from the centre of every point of every body over every
    joint angle, by the chain of pivots: a joint whose axis runs through the point measured
    from keeps every distance from it, and past any other, a point is at most the pivot's
    distance plus its own distance from the pivot (which that joint keeps). Exact for a
    stretched arm, a few millimetres over otherwise."""
    children: dict[int | None, list[int]] = {}
    for i, body in enumerate(bodies):
        children.setdefault(body.parent, []).append(i)
    moving = [i for i in range(len(bodies)) if bodies[i].pivot is not None]
    if not moving:
        raise ValueError("an arm needs a jointed body to be framed")
    first = moving[0]
    pivot, axis = bodies[first].pivot, bodies[first].axis
    assert pivot is not None and axis is not None
    shoulder = next((i for i in moving if i != first), first)
    shoulder_pivot = bodies[shoulder].pivot
    assert shoulder_pivot is not None
    center = _nearest_on_axis(shoulder_pivot, pivot, axis)

    def on_axis(point: Vec3, body: ArmBody) -> bool:
        assert body.pivot is not None and body.axis is not None
        return _norm(_sub(point, _nearest_on_axis(point, body.pivot, body.axis))) < 1e-9

    def farthest(b: int, point: Vec3) -> float:
        """Farthest from `point` (fixed to b's parent) that b and what hangs from it reach."""
        body = bodies[b]
        if body.pivot is not None and not on_axis(point, body):
            return _norm(_sub(body.pivot, point)) + farthest(b, body.pivot)
        own = [_norm(_sub(ball.center, point)) + ball.radius for ball in body.balls]
        return max(own + [farthest(c, point) for c in children.get(b, [])] + [0.0])

    radius = max(farthest(root, center) for root in children.get(None, []))
    return Reach(center, radius)


@dataclass(frozen=True)
class EyePose:
    """Where the 3D view's eye sits and what it looks at (world coordinates, metres)."""

    position: Vec3
    look_target: Vec3
    eye_up: Vec3


def framing_half_angle(fov_y_rad: float = EYE_FOV_Y_RAD, aspect: float = MIN_VIEW_ASPECT) -> float:
    """The half angle of the cone a view of `aspect` (width / height) holds whole."""
    half_y = fov_y_rad / 2.0
    return min(half_y, math.atan(aspect * math.tan(half_y)))


def framing_eye(ball: Reach) -> EyePose:
    """An eye from which the whole of `ball` is in view (in any 3D view at least
    MIN_VIEW_ASPECT wide for its height), looking at its centre along EYE_DIRECTION."""
    distance = ball.radius / math.sin(framing_half_angle()) * (1.0 + EYE_MARGIN)
    d = _unit(EYE_DIRECTION)
    c = ball.center
    position = (c[0] - distance * d[0], c[1] - distance * d[1], c[2] - distance * d[2])
    return EyePose(position=position, look_target=c, eye_up=WORLD_UP)


def arm_view(name: str, contents: Sequence[str], eye: EyePose) -> rrb.Spatial3DView:
    """The 3D view of the arm, its eye pinned where it frames every pose."""
    return rrb.Spatial3DView(
        origin="/",
        contents=list(contents),
        name=name,
        eye_controls=rrb.EyeControls3D(
            kind="Orbital",
            position=eye.position,
            look_target=eye.look_target,
            eye_up=eye.eye_up,
        ),
    )


#: A plot's time axis: the recording's whole time line, whatever span the plot's own data has.
WHOLE_RUN = encodings.TimeRange(
    start=encodings.TimeRangeBoundary.infinite(), end=encodings.TimeRangeBoundary.infinite()
)


def series_view(origin: str, name: str) -> rrb.TimeSeriesView:
    """A plot over the recording's whole time axis (in seconds on a duration timeline), its
    legend hidden: series are told apart by colour (the titles and docs give the key) and by
    hovering."""
    return rrb.TimeSeriesView(
        origin=origin,
        name=name,
        axis_x=rrb.TimeAxis(view_range=WHOLE_RUN),
        plot_legend=rrb.PlotLegend(visible=False),
    )


def time_panel(timeline: str, live: bool) -> rrb.TimePanel:
    """The time panel on `timeline`, collapsed; a live stream's follows the newest data (a
    file plays from its start, the viewer's own default)."""
    return rrb.TimePanel(
        timeline=timeline, state="collapsed", play_state="following" if live else None
    )
