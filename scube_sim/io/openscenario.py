"""ASAM OpenSCENARIO 1.x (.xosc): the ego's timed trajectory in, a replayed ego trajectory out.

Read (`read_openscenario`; `sim.sources.TrajectorySource.from_openscenario` is the pose source): the ego entity's Init ``TeleportAction``
(a ``WorldPosition``) and its ``FollowTrajectoryAction``s whose ``Trajectory`` is a timed
``Polyline`` of ``WorldPosition`` vertices, given inline (1.0), through a ``TrajectoryRef`` (1.1+)
or through a ``CatalogReference`` into a trajectory catalog (``CatalogLocations/
TrajectoryCatalog/Directory``, resolved relative to the scenario file). Maneuvers may also come
from a maneuver catalog. ``$name`` parameters and ``${...}`` arithmetic expressions are resolved.

- Frames: OpenSCENARIO's world frame (ISO 8855: right-handed, z up, metres) is ours; a vertex's
  heading/pitch/roll (radians) turn as ``R = Rz(h) Ry(p) Rx(r)`` (`transforms.hpr_to_rotmat`).
- Missing attributes: z, p, r default to 0 (there is no road surface to align to); a missing
  heading follows the polyline (the direction to the next vertex), as simulators do.
- Times: a vertex at ``time`` is reached at simulation time ``scale * time + offset`` (the
  action's ``Timing``); with ``domainAbsoluteRelative="relative"`` the action's start is added,
  known only when its event's and act's start triggers are simulation-time conditions. When the
  trajectory starts after 0 s, the Init teleport pose is put first at 0 s (the ego is there when
  the simulation starts), and the pose source moves linearly / by SLERP from it to the first
  vertex, like between any two vertices (`sim.sources.TrajectorySource`).
- Not read (clear errors): Clothoid / Nurbs shapes, positions other than WorldPosition, untimed
  trajectories (``TimeReference/None``), a non-zero ``initialDistanceOffset``. ``closed`` is
  ignored; maneuver groups count for the ego only through ``Actors/EntityRef`` (not
  EntitySelection / ByType / selectTriggeringEntities).

Write (`write_openscenario`): times (T,) and (T, 4, 4) ego-to-world poses as a schema-valid
OpenSCENARIO 1.0-1.3 file: FileHeader, an empty RoadNetwork, the ego as a Vehicle, an Init
TeleportAction to the first pose, and one Story/Act/ManeuverGroup/Maneuver/Event/Action with a
FollowTrajectoryAction (absolute Timing, scale 1, offset 0; ``followingMode`` as chosen). The
bytes depend only on the arguments (the header date is fixed unless given).
"""

from __future__ import annotations

import ast
import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np
from defusedxml.ElementTree import parse as safe_parse  # entity expansion and external entities refused

from ..atomic import atomic_path
from ..errors import InputError, NotFoundError
from ..transforms import check_pose, hpr_to_rotmat, make_pose, rotmat_to_hpr

__all__ = ["OpenScenarioTrajectory", "read_openscenario", "write_openscenario"]

EGO_NAMES = ("Ego", "ego")
FOLLOWING_MODES = ("position", "follow")
DEFAULT_DATE = "1970-01-01T00:00:00"


@dataclass
class OpenScenarioTrajectory:
    """The ego's path from an .xosc file.

    times: (T,) float64 strictly increasing simulation seconds; poses: (T, 4, 4) float64
    ego-to-world. initial_pose: (4, 4) from the Init TeleportAction (None if there is none).
    entities: every ScenarioObject name; trajectories: the names of the trajectories followed;
    following_modes: their ``followingMode`` values."""

    path: Path
    entity: str
    entities: list[str]
    times: np.ndarray
    poses: np.ndarray
    initial_pose: np.ndarray | None = None
    trajectories: list[str] = field(default_factory=list)
    following_modes: list[str] = field(default_factory=list)


# --- parameters and expressions ------------------------------------------------------------

_FUNCS = {"round": lambda x: float(math.floor(x + 0.5)), "floor": math.floor, "ceil": math.ceil,
          "sqrt": math.sqrt, "pow": math.pow, "min": min, "max": max}
_BINOPS = {ast.Add: lambda a, b: a + b, ast.Sub: lambda a, b: a - b, ast.Mult: lambda a, b: a * b,
           ast.Div: lambda a, b: a / b, ast.Mod: math.fmod, ast.Pow: math.pow}


class _Scope:
    """Parameter values visible to one part of a file (names without the leading ``$``)."""

    def __init__(self, path: Path, values: dict[str, str] | None = None):
        self.path = path
        self.values = dict(values or {})

    def child(self) -> "_Scope":
        return _Scope(self.path, self.values)

    def declare(self, decls: ET.Element | None, where: str) -> None:
        for d in [] if decls is None else decls.findall("ParameterDeclaration"):
            name = d.get("name")
            if not name or d.get("value") is None:
                raise InputError(f"{self.path}: {where}: ParameterDeclaration needs 'name' and 'value'")
            self.values[name.lstrip("$")] = self.resolve(d.get("value"), f"{where}: parameter {name!r}")

    def resolve(self, text: str, where: str) -> str:
        """An attribute's text with a ``$name`` reference or a ``${expr}`` expression evaluated."""
        text = text.strip()
        if text.startswith("${") and text.endswith("}"):
            return repr(self._expression(text[2:-1], where))
        if text.startswith("$"):
            name = text[1:]
            if name not in self.values:
                raise InputError(f"{self.path}: {where}: parameter ${name} is not declared "
                                 f"(declared: {sorted(self.values) or 'none'})")
            return self.values[name]
        return text

    def _expression(self, expr: str, where: str) -> float:
        py = re.sub(r"\$([A-Za-z_][A-Za-z0-9_]*)", r"__p_\1", expr)
        try:
            tree = ast.parse(py, mode="eval")
        except SyntaxError:
            raise InputError(f"{self.path}: {where}: cannot parse expression ${{{expr}}}") from None

        def ev(n):
            if isinstance(n, ast.Expression):
                return ev(n.body)
            if isinstance(n, ast.Constant) and isinstance(n.value, (int, float)) and not isinstance(n.value, bool):
                return float(n.value)
            if isinstance(n, ast.Name):
                if n.id in ("true", "false"):
                    return float(n.id == "true")
                name = n.id[4:] if n.id.startswith("__p_") else n.id
                if not n.id.startswith("__p_") or name not in self.values:
                    raise InputError(f"{self.path}: {where}: unknown name {n.id.replace('__p_', '$')!r} in "
                                     f"${{{expr}}} (declared: {sorted(self.values) or 'none'})")
                try:
                    return float(self.values[name])
                except ValueError:
                    raise InputError(f"{self.path}: {where}: parameter ${name} = {self.values[name]!r} "
                                     f"is not a number") from None
            if isinstance(n, ast.BinOp) and type(n.op) in _BINOPS:
                return _BINOPS[type(n.op)](ev(n.left), ev(n.right))
            if isinstance(n, ast.UnaryOp) and isinstance(n.op, (ast.USub, ast.UAdd, ast.Not)):
                v = ev(n.operand)
                return -v if isinstance(n.op, ast.USub) else (v if isinstance(n.op, ast.UAdd) else float(not v))
            if isinstance(n, ast.BoolOp):
                vals = [bool(ev(v)) for v in n.values]
                return float(all(vals) if isinstance(n.op, ast.And) else any(vals))
            if (isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id in _FUNCS
                    and not n.keywords):
                return float(_FUNCS[n.func.id](*[ev(a) for a in n.args]))
            raise InputError(f"{self.path}: {where}: unsupported expression ${{{expr}}} (numbers, parameters, "
                             f"+ - * / % **, not/and/or and {sorted(_FUNCS)} only)")

        try:
            return ev(tree)
        except (ZeroDivisionError, ValueError, OverflowError, TypeError) as exc:
            if isinstance(exc, InputError):
                raise
            raise InputError(f"{self.path}: {where}: cannot evaluate ${{{expr}}} ({exc})") from None

    def attr(self, el: ET.Element, key: str, where: str, default: str | None = None) -> str:
        v = el.get(key)
        if v is None:
            if default is None:
                raise InputError(f"{self.path}: {where}: {el.tag} has no attribute {key!r}")
            return default
        return self.resolve(v, f"{where}: {el.tag}@{key}")

    def number(self, el: ET.Element, key: str, where: str, default: float | None = None) -> float | None:
        v = el.get(key)
        if v is None:
            return default
        text = self.resolve(v, f"{where}: {el.tag}@{key}")
        try:
            x = float(text)
        except ValueError:
            raise InputError(f"{self.path}: {where}: {el.tag}@{key} = {text!r} is not a number") from None
        if not math.isfinite(x):
            raise InputError(f"{self.path}: {where}: {el.tag}@{key} = {text!r} is not finite")
        return x


# --- reading -----------------------------------------------------------------------------------

def _parse(path: Path) -> ET.Element:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such OpenSCENARIO file")
    try:
        root = safe_parse(path).getroot()
    except ET.ParseError as exc:
        raise InputError(f"{path}: not well-formed XML ({exc})") from None
    if root.tag != "OpenSCENARIO":
        raise InputError(f"{path}: root element is <{root.tag}>, expected <OpenSCENARIO>")
    header = root.find("FileHeader")
    if header is None:
        raise InputError(f"{path}: no FileHeader (not an OpenSCENARIO 1.x file?)")
    if header.get("revMajor", "1").strip() != "1":
        raise InputError(f"{path}: FileHeader revMajor {header.get('revMajor')!r}: only OpenSCENARIO 1.x is read "
                         f"(2.0 is a different language)")
    return root


def _child(el: ET.Element, tag: str, scope: _Scope, where: str) -> ET.Element:
    c = el.find(tag)
    if c is None:
        raise InputError(f"{scope.path}: {where}: {el.tag} has no {tag}")
    return c


def _world_position(pos: ET.Element, scope: _Scope, where: str) -> tuple[np.ndarray, float | None, float, float]:
    """Position element -> (xyz, heading or None when absent, pitch, roll)."""
    wp = pos.find("WorldPosition")
    if wp is None:
        kinds = [c.tag for c in pos] or ["nothing"]
        raise InputError(f"{scope.path}: {where}: the position is a {kinds[0]}; only WorldPosition can be placed "
                         f"without a road network")
    if wp.get("x") is None or wp.get("y") is None:
        raise InputError(f"{scope.path}: {where}: WorldPosition needs x and y")
    xyz = np.array([scope.number(wp, k, where, 0.0) for k in "xyz"], np.float64)
    return xyz, scope.number(wp, "h", where), scope.number(wp, "p", where, 0.0), scope.number(wp, "r", where, 0.0)


class _Catalogs:
    """Entries of the catalogs a scenario names, loaded on first use."""

    def __init__(self, root: ET.Element, scope: _Scope):
        self.path = scope.path
        self.dirs: dict[str, Path] = {}
        locs = root.find("CatalogLocations")
        for loc in [] if locs is None else list(locs):
            d = loc.find("Directory")
            if d is not None and d.get("path"):
                p = Path(scope.resolve(d.get("path"), f"CatalogLocations/{loc.tag}"))
                self.dirs[loc.tag] = p if p.is_absolute() else self.path.parent / p
        self._cache: dict[str, dict[str, ET.Element]] = {}

    def _load(self, kind: str) -> dict[str, ET.Element]:
        if kind not in self._cache:
            d = self.dirs.get(kind)
            if d is None:
                raise InputError(f"{self.path}: a CatalogReference needs CatalogLocations/{kind}/Directory "
                                 f"(found: {sorted(self.dirs) or 'none'})")
            if not d.is_dir():
                raise InputError(f"{self.path}: CatalogLocations/{kind}: {d} is not a folder")
            found: dict[str, ET.Element] = {}
            for f in sorted(d.glob("*.xosc")):
                try:
                    cat = safe_parse(f).getroot().find("Catalog")
                except ET.ParseError as exc:
                    raise InputError(f"{f}: not well-formed XML ({exc})") from None
                if cat is not None and cat.get("name"):
                    found.setdefault(cat.get("name"), cat)
            self._cache[kind] = found
        return self._cache[kind]

    def entry(self, ref: ET.Element, kind: str, tag: str, scope: _Scope, where: str) -> tuple[ET.Element, _Scope]:
        """The catalog entry a CatalogReference names and the scope its parameters make."""
        cname = scope.attr(ref, "catalogName", where)
        ename = scope.attr(ref, "entryName", where)
        cats = self._load(kind)
        if cname not in cats:
            raise NotFoundError(f"{self.path}: {where}: catalog {cname!r} not found in {self.dirs[kind]} "
                                f"(catalogs there: {sorted(cats) or 'none'})")
        entries = {e.get("name"): e for e in cats[cname].findall(tag)}
        if ename not in entries:
            raise NotFoundError(f"{self.path}: {where}: catalog {cname!r} has no {tag} {ename!r} "
                                f"({tag} entries: {sorted(k for k in entries if k) or 'none'})")
        entry = entries[ename]
        inner = scope.child()
        inner.declare(entry.find("ParameterDeclarations"), f"{where}: catalog entry {cname}/{ename}")
        assigns = ref.find("ParameterAssignments")
        for a in [] if assigns is None else assigns.findall("ParameterAssignment"):
            inner.values[scope.attr(a, "parameterRef", where).lstrip("$")] = scope.attr(a, "value", where)
        return entry, inner


def _start_time(trigger: ET.Element | None, scope: _Scope, where: str) -> float | None:
    """The simulation time a start trigger fires at, when it is one simulation-time condition
    (none: at once, 0); None when it depends on anything else."""
    if trigger is None:
        return 0.0
    groups = trigger.findall("ConditionGroup")
    if not groups:
        return 0.0
    if len(groups) != 1 or len(groups[0].findall("Condition")) != 1:
        return None
    cond = groups[0].find("Condition")
    stc = cond.find("ByValueCondition/SimulationTimeCondition")
    value = None if stc is None else scope.number(stc, "value", where)
    return None if value is None else value + scope.number(cond, "delay", where, 0.0)


def _polyline(traj: ET.Element, scope: _Scope, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Trajectory -> vertex times (T,) as written and (T, 4, 4) poses."""
    shape = _child(traj, "Shape", scope, where)
    poly = shape.find("Polyline")
    if poly is None:
        kinds = [c.tag for c in shape] or ["nothing"]
        raise InputError(f"{scope.path}: {where}: trajectory shape is {kinds[0]}; only Polyline is read")
    verts = poly.findall("Vertex")
    if len(verts) < 1:
        raise InputError(f"{scope.path}: {where}: Polyline has no Vertex")
    times, xyz, hpr = [], [], []
    for i, v in enumerate(verts):
        w = f"{where}: Vertex {i}"
        t = scope.number(v, "time", w)
        if t is None:
            raise InputError(f"{scope.path}: {w}: no 'time'; a pose source needs a timed trajectory")
        p, h, pitch, roll = _world_position(_child(v, "Position", scope, w), scope, w)
        times.append(t)
        xyz.append(p)
        hpr.append((h, pitch, roll))
    xyz = np.array(xyz)
    poses = np.empty((len(verts), 4, 4))
    for i, (h, pitch, roll) in enumerate(hpr):
        if h is None:  # heading along the path: towards the next vertex (the last: from the previous)
            d = xyz[min(i + 1, len(xyz) - 1)] - xyz[max(min(i, len(xyz) - 2), 0)]
            h = math.atan2(d[1], d[0]) if np.hypot(d[0], d[1]) > 1e-9 else 0.0
        poses[i] = make_pose(hpr_to_rotmat(h, pitch, roll), xyz[i])
    return np.array(times, np.float64), poses


@dataclass
class _Follow:
    times: np.ndarray
    poses: np.ndarray
    name: str
    mode: str


def _follow_action(fta: ET.Element, scope: _Scope, catalogs: _Catalogs, start: float | None, where: str) -> _Follow:
    if scope.number(fta, "initialDistanceOffset", where, 0.0) != 0.0:
        raise InputError(f"{scope.path}: {where}: FollowTrajectoryAction@initialDistanceOffset is not supported; "
                         f"cut the polyline instead")
    holder = fta.find("TrajectoryRef")
    holder = fta if holder is None else holder
    traj, tscope = holder.find("Trajectory"), scope
    if traj is None:
        ref = holder.find("CatalogReference")
        if ref is None:
            raise InputError(f"{scope.path}: {where}: FollowTrajectoryAction has no Trajectory or CatalogReference")
        traj, tscope = catalogs.entry(ref, "TrajectoryCatalog", "Trajectory", scope, where)  # declares its parameters
    else:
        tscope = scope.child()
        tscope.declare(traj.find("ParameterDeclarations"), f"{where}: trajectory {traj.get('name')!r}")
    name = tscope.attr(traj, "name", where, "")
    vt, poses = _polyline(traj, tscope, f"{where}: trajectory {name!r}")
    tref = _child(fta, "TimeReference", scope, where)
    timing = tref.find("Timing")
    if timing is None:
        raise InputError(f"{scope.path}: {where}: trajectory {name!r} has TimeReference/None: its vertex times "
                         f"are not used, so it gives no timed poses")
    domain = scope.attr(timing, "domainAbsoluteRelative", where)
    scale = scope.number(timing, "scale", where, 1.0)
    offset = scope.number(timing, "offset", where, 0.0)
    if not scale > 0:
        raise InputError(f"{scope.path}: {where}: Timing@scale must be > 0, got {scale}")
    times = scale * vt + offset
    if domain == "relative":
        if start is None:
            raise InputError(f"{scope.path}: {where}: relative Timing needs the action's start time, known only when "
                             f"its event's and act's start triggers are SimulationTimeConditions")
        times = times + start
    elif domain != "absolute":
        raise InputError(f"{scope.path}: {where}: Timing@domainAbsoluteRelative {domain!r}: expected "
                         f"'absolute' or 'relative'")
    mode_el = fta.find("TrajectoryFollowingMode")
    mode = scope.attr(mode_el, "followingMode", where, "position") if mode_el is not None else "position"
    return _Follow(times, poses, name, mode)


def _entity_names(root: ET.Element, scope: _Scope) -> list[str]:
    return [scope.attr(o, "name", "Entities") for o in root.findall("Entities/ScenarioObject")]


def _choose_entity(path: Path, names: list[str], entity: str | None) -> str:
    if not names:
        raise InputError(f"{path}: Entities has no ScenarioObject (no ego to follow)")
    if entity is not None:
        if entity not in names:
            raise NotFoundError(f"{path}: entity {entity!r} not found; the entities are {names}")
        return entity
    return next((n for n in names if n in EGO_NAMES), names[0])


def read_openscenario(path: str | Path, entity: str | None = None) -> OpenScenarioTrajectory:
    """The trajectory an entity follows in an OpenSCENARIO 1.x file.

    entity: a ScenarioObject name; default the one named 'Ego' or 'ego', else the first."""
    path = Path(path)
    root = _parse(path)
    scope = _Scope(path)
    scope.declare(root.find("ParameterDeclarations"), "ParameterDeclarations")
    names = _entity_names(root, scope)
    ego = _choose_entity(path, names, entity)
    catalogs = _Catalogs(root, scope)
    sb = root.find("Storyboard")
    if sb is None:
        raise InputError(f"{path}: no Storyboard")

    def is_ego(el, key="entityRef"):
        return el.get(key) is not None and scope.resolve(el.get(key), f"{el.tag}@{key}") == ego

    follows: list[_Follow] = []
    initial, teleport_error = None, None
    for i, priv in enumerate(sb.findall("Init/Actions/Private")):
        if not is_ego(priv):
            continue
        for j, pa in enumerate(priv.findall("PrivateAction")):
            where = f"Init/Private[{ego}]/PrivateAction {j}"
            tp = pa.find("TeleportAction")
            if tp is not None:
                try:
                    xyz, h, p, r = _world_position(_child(tp, "Position", scope, where), scope, where)
                    initial = make_pose(hpr_to_rotmat(h or 0.0, p, r), xyz)
                except InputError as exc:  # needed only if the trajectory starts after 0 s
                    teleport_error = exc
            fta = pa.find("RoutingAction/FollowTrajectoryAction")
            if fta is not None:
                follows.append(_follow_action(fta, scope, catalogs, 0.0, where))

    for s_i, story in enumerate(sb.findall("Story")):
        for a_i, act in enumerate(story.findall("Act")):
            act_name = f"Story {story.get('name', s_i)!s}/Act {act.get('name', a_i)!s}"
            act_start = _start_time(act.find("StartTrigger"), scope, act_name)
            for g_i, group in enumerate(act.findall("ManeuverGroup")):
                gwhere = f"{act_name}/ManeuverGroup {group.get('name', g_i)!s}"
                if not any(is_ego(r) for r in group.findall("Actors/EntityRef")):
                    continue
                maneuvers = [(m, scope) for m in group.findall("Maneuver")]
                for ref in group.findall("CatalogReference"):
                    maneuvers.append(catalogs.entry(ref, "ManeuverCatalog", "Maneuver", scope, gwhere))
                for m, mscope in maneuvers:
                    mwhere = f"{gwhere}/Maneuver {m.get('name', '?')}"
                    if mscope is scope:
                        mscope = scope.child()
                    mscope.declare(m.find("ParameterDeclarations"), mwhere)
                    for event in m.findall("Event"):
                        ewhere = f"{mwhere}/Event {event.get('name', '?')}"
                        ev_start = _start_time(event.find("StartTrigger"), mscope, ewhere)
                        start = None if act_start is None or ev_start is None else max(act_start, ev_start)
                        for action in event.findall("Action"):
                            fta = action.find("PrivateAction/RoutingAction/FollowTrajectoryAction")
                            if fta is not None:
                                follows.append(_follow_action(fta, mscope, catalogs, start,
                                                              f"{ewhere}/Action {action.get('name', '?')}"))

    if not follows:
        having = [n for n in names if n != ego and _has_trajectory(sb, scope, n)]
        hint = f"; entities with one: {having}" if having else ""
        raise InputError(f"{path}: entity {ego!r} follows no FollowTrajectoryAction (entities: {names}){hint}")
    follows.sort(key=lambda f: f.times[0])
    for a, b in zip(follows, follows[1:]):
        if b.times[0] < a.times[-1]:
            raise InputError(f"{path}: trajectories {a.name!r} ({a.times[0]:g}-{a.times[-1]:g} s) and {b.name!r} "
                             f"({b.times[0]:g}-{b.times[-1]:g} s) of {ego!r} overlap in time")
    times = np.concatenate([f.times for f in follows])
    poses = np.concatenate([f.poses for f in follows])
    keep = np.concatenate([[True], np.diff(times) > 0])  # a vertex shared by consecutive trajectories
    dup = ~keep & np.concatenate([[False], np.any(np.abs(np.diff(poses, axis=0)) > 1e-9, axis=(1, 2))])
    if np.any(dup):
        raise InputError(f"{path}: two different poses of {ego!r} at {times[np.argmax(dup)]:g} s")
    if np.any(np.diff(times) < 0):
        raise InputError(f"{path}: vertex times of {ego!r} must increase")
    times, poses = times[keep], poses[keep]
    if times[0] > 0.0:
        if teleport_error is not None:
            raise teleport_error
        if initial is not None:  # the ego stands at its Init position when the simulation starts
            times, poses = np.concatenate([[0.0], times]), np.concatenate([initial[None], poses])
    return OpenScenarioTrajectory(path, ego, names, times, poses, initial, [f.name for f in follows],
                                  [f.mode for f in follows])


def _has_trajectory(sb: ET.Element, scope: _Scope, name: str) -> bool:
    for group in sb.iter("ManeuverGroup"):
        refs = [scope.resolve(r.get("entityRef"), "EntityRef") for r in group.findall("Actors/EntityRef")
                if r.get("entityRef")]
        if name in refs and next(group.iter("FollowTrajectoryAction"), None) is not None:
            return True
    return False


# --- writing -----------------------------------------------------------------------------------

def _num(x: float) -> str:
    return repr(float(x))  # the shortest text that reads back to the same double


def _world_position_el(parent: ET.Element, pose: np.ndarray) -> None:
    h, p, r = rotmat_to_hpr(pose[:3, :3])
    x, y, z = pose[:3, 3]
    ET.SubElement(ET.SubElement(parent, "Position"), "WorldPosition",
                  {"x": _num(x), "y": _num(y), "z": _num(z), "h": _num(h), "p": _num(p), "r": _num(r)})


def _sim_time_trigger(parent: ET.Element, tag: str, name: str, value: float) -> None:
    cond = ET.SubElement(ET.SubElement(ET.SubElement(parent, tag), "ConditionGroup"), "Condition",
                         {"name": name, "delay": "0", "conditionEdge": "none"})
    ET.SubElement(ET.SubElement(cond, "ByValueCondition"), "SimulationTimeCondition",
                  {"value": _num(value), "rule": "greaterThan"})


def write_openscenario(path: str | Path, times, poses, *, entity: str = "Ego",
                       trajectory_name: str = "ego_trajectory", following_mode: str = "position",
                       rev_minor: int = 2, description: str = "scube-sim replayed ego trajectory",
                       author: str = "scube-sim", date: str | datetime | None = None,
                       vehicle_size=(4.6, 1.9, 1.6)) -> Path:
    """Write an ego trajectory as an OpenSCENARIO 1.`rev_minor` file (0..3; valid against ASAM's
    schema of that version).

    times: (T,) strictly increasing seconds (simulation time; T >= 2); poses: (T, 4, 4)
    ego-to-world. following_mode: 'position' (the ego is exactly on the path) or 'follow'.
    vehicle_size: the ego's bounding box (length, width, height) metres, centred on its origin
    in x and y, standing on z = 0. date: FileHeader date (default a fixed one, so the bytes
    depend only on the trajectory)."""
    path = Path(path)
    times = np.asarray(times, np.float64)
    poses = np.asarray(poses, np.float64)
    if times.ndim != 1 or times.shape[0] < 2:
        raise InputError(f"write_openscenario: times: expected shape (T,) with T >= 2, got {times.shape}")
    if poses.shape != (times.shape[0], 4, 4):
        raise InputError(f"write_openscenario: poses: expected shape ({times.shape[0]}, 4, 4), got {poses.shape}")
    if not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
        raise InputError("write_openscenario: times must be finite and strictly increasing")
    for i, p in enumerate(poses):
        check_pose(p, f"write_openscenario: pose {i}")
    if rev_minor not in (0, 1, 2, 3):
        raise InputError(f"write_openscenario: rev_minor: expected 0, 1, 2 or 3 (OpenSCENARIO 1.0-1.3), got {rev_minor}")
    if following_mode not in FOLLOWING_MODES:
        raise InputError(f"write_openscenario: following_mode: expected one of {FOLLOWING_MODES}, got {following_mode!r}")
    length, width, height = (float(v) for v in vehicle_size)
    if isinstance(date, datetime):
        date = date.replace(microsecond=0).isoformat()

    root = ET.Element("OpenSCENARIO")
    ET.SubElement(root, "FileHeader", {"revMajor": "1", "revMinor": str(rev_minor), "date": date or DEFAULT_DATE,
                                       "description": description, "author": author})
    ET.SubElement(root, "ParameterDeclarations")
    ET.SubElement(root, "CatalogLocations")
    ET.SubElement(root, "RoadNetwork")  # no road: every position is a WorldPosition
    obj = ET.SubElement(ET.SubElement(root, "Entities"), "ScenarioObject", {"name": entity})
    veh = ET.SubElement(obj, "Vehicle", {"name": f"{entity}_vehicle", "vehicleCategory": "car"})
    bb = ET.SubElement(veh, "BoundingBox")
    ET.SubElement(bb, "Center", {"x": "0", "y": "0", "z": _num(height / 2)})
    ET.SubElement(bb, "Dimensions", {"width": _num(width), "length": _num(length), "height": _num(height)})
    ET.SubElement(veh, "Performance", {"maxSpeed": "70", "maxAcceleration": "10", "maxDeceleration": "10"})
    axles = ET.SubElement(veh, "Axles")
    ET.SubElement(axles, "FrontAxle", {"maxSteering": "0.5", "wheelDiameter": "0.7", "trackWidth": _num(width * 0.85),
                                       "positionX": _num(length * 0.3), "positionZ": "0.35"})
    ET.SubElement(axles, "RearAxle", {"maxSteering": "0", "wheelDiameter": "0.7", "trackWidth": _num(width * 0.85),
                                      "positionX": _num(-length * 0.3), "positionZ": "0.35"})
    ET.SubElement(veh, "Properties")

    sb = ET.SubElement(root, "Storyboard")
    priv = ET.SubElement(ET.SubElement(ET.SubElement(sb, "Init"), "Actions"), "Private", {"entityRef": entity})
    _world_position_el(ET.SubElement(ET.SubElement(priv, "PrivateAction"), "TeleportAction"), poses[0])
    act = ET.SubElement(ET.SubElement(sb, "Story", {"name": "replay"}), "Act", {"name": "replay"})
    group = ET.SubElement(act, "ManeuverGroup", {"name": "ego", "maximumExecutionCount": "1"})
    ET.SubElement(ET.SubElement(group, "Actors", {"selectTriggeringEntities": "false"}), "EntityRef",
                  {"entityRef": entity})
    event = ET.SubElement(ET.SubElement(group, "Maneuver", {"name": "follow"}), "Event",
                          {"name": "follow", "priority": "overwrite" if rev_minor < 2 else "override",
                           "maximumExecutionCount": "1"})
    fta = ET.SubElement(ET.SubElement(ET.SubElement(ET.SubElement(event, "Action", {"name": "follow_trajectory"}),
                                                    "PrivateAction"), "RoutingAction"), "FollowTrajectoryAction")
    holder = fta if rev_minor == 0 else ET.SubElement(fta, "TrajectoryRef")  # 1.1 moved it into TrajectoryRef
    traj = ET.SubElement(holder, "Trajectory", {"name": trajectory_name, "closed": "false"})
    poly = ET.SubElement(ET.SubElement(traj, "Shape"), "Polyline")
    for t, pose in zip(times, poses):
        _world_position_el(ET.SubElement(poly, "Vertex", {"time": _num(t)}), pose)
    ET.SubElement(ET.SubElement(fta, "TimeReference"), "Timing",
                  {"domainAbsoluteRelative": "absolute", "scale": "1", "offset": "0"})
    ET.SubElement(fta, "TrajectoryFollowingMode", {"followingMode": following_mode})
    # start at once (the usual "simulation time > 0"; 1.0 has no greaterOrEqual): with absolute
    # timing the vertex times, not the start, say where the ego is
    _sim_time_trigger(event, "StartTrigger", "start", 0.0)
    _sim_time_trigger(act, "StartTrigger", "act_start", 0.0)
    _sim_time_trigger(sb, "StopTrigger", "end", float(times[-1]))

    ET.indent(root, space="  ")
    data = ET.tostring(root, encoding="utf-8", xml_declaration=True) + b"\n"
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
    return path
