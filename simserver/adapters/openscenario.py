"""A reader of the ASAM OpenSCENARIO 1.x subset simserver plays (issue 31; docs/openscenario.md).

The file is read with expat (every element keeps its line, as ``adapters.opendrive``), into
a small tree of :class:`Node`; then the subset is read from it into plain dataclasses:
parameters (``$name`` references and ``${...}`` expressions, :func:`evaluate`, a parser of
its own: no ``eval``), vehicle catalogs and ``CatalogReference``, the road file, the
entities, ``Init`` and the ``Storyboard`` (stories, acts, maneuver groups, maneuvers,
events, their actions and their start and stop triggers).

Errors (:class:`XoscError`) are one line: ``file:line: <Element>: message``.

**The rule for elements outside the subset** (docs/openscenario.md):

- an element that does not move a car (appearance, scene graph, properties, the
  environment, controllers left at the default, a trailer hitch, ...) is *ignored*: it is
  reported once per element name with its lines (:attr:`Scenario.ignored`, printed as
  warnings by the runner);
- an element that would move a car or decide when something happens (an action,
  a condition, a position, an entity kind outside the subset) is *refused*: the file is
  not run (:class:`XoscError` naming the file, the line and the element), because playing
  the rest would be a different scenario.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from xml.parsers import expat

from simserver.adapters.validate import ConfigError

MAX_XOSC_BYTES = 32 << 20
"""Largest ``.xosc`` file read (32 MiB; the scenarios of the field are a few kB)."""


class XoscError(ConfigError):
    """An OpenSCENARIO file outside the subset or malformed: ``file:line: <Element>: ...``."""


# ------------------------------------------------------------------------------ the tree
@dataclass
class Node:
    """One XML element: its tag, attributes, line and children (and the file it is in)."""

    tag: str
    attrs: dict[str, str]
    line: int
    path: Path
    children: list[Node] = field(default_factory=list)

    def where(self) -> str:
        return f"{self.path}:{self.line}: <{self.tag}>"

    def fail(self, message: str) -> XoscError:
        return XoscError(f"{self.where()}: {message}")

    def child(self, tag: str, required: bool = True) -> Node | None:
        for c in self.children:
            if c.tag == tag:
                return c
        if required:
            raise self.fail(f"missing child <{tag}>")
        return None

    def all(self, tag: str) -> list[Node]:
        return [c for c in self.children if c.tag == tag]

    def only_child(self) -> Node:
        if len(self.children) != 1:
            raise self.fail(f"expected exactly one child element, found {len(self.children)}")
        return self.children[0]


def read_tree(path: Path) -> Node:
    """Parse an XML file into :class:`Node` s with their lines (errors name file and line)."""
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise XoscError(f"{path}: cannot read: {exc.strerror or exc}") from None
    if size > MAX_XOSC_BYTES:
        raise XoscError(f"{path}: {size} bytes, more than {MAX_XOSC_BYTES}")
    parser = expat.ParserCreate()
    stack: list[Node] = []
    root: list[Node] = []

    def start(tag: str, attrs: dict[str, str]) -> None:
        node = Node(tag, dict(attrs), parser.CurrentLineNumber, path)
        if stack:
            stack[-1].children.append(node)
        else:
            root.append(node)
        stack.append(node)

    def end(_tag: str) -> None:
        stack.pop()

    def entity(*_: Any) -> None:  # no entity expansion (billion laughs)
        raise XoscError(f"{path}:{parser.CurrentLineNumber}: entity declarations are refused")

    parser.StartElementHandler = start
    parser.EndElementHandler = end
    parser.EntityDeclHandler = entity
    try:
        parser.Parse(path.read_bytes(), True)
    except expat.ExpatError as exc:
        raise XoscError(f"{path}:{exc.lineno}: not well-formed XML: "
                        f"{expat.ErrorString(exc.code)}") from None
    return root[0]


# ------------------------------------------------------------------ parameter expressions
_TOKEN = re.compile(r"\s*(?:(\d+\.?\d*(?:[eE][+-]?\d+)?|\.\d+(?:[eE][+-]?\d+)?)"
                    r"|(\$[A-Za-z_][A-Za-z0-9_]*)|(\*\*|[-+*/%()]))")


class ExpressionError(ValueError):
    """A ``${...}`` expression that does not parse or evaluate (no location: the caller's)."""


def _tokens(text: str) -> list[tuple[str, Any]]:
    out: list[tuple[str, Any]] = []
    pos = 0
    text = text.rstrip()
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None or m.end() == pos:
            raise ExpressionError(f"unexpected {text[pos:].strip()[:20]!r} at character {pos}")
        num, ref, op = m.groups()
        if num is not None:
            out.append(("num", float(num)))
        elif ref is not None:
            out.append(("ref", ref[1:]))
        else:
            if op == "**":
                raise ExpressionError("'**' is not an operator of the subset "
                                      "(+ - * / % and parentheses)")
            out.append(("op", op))
        pos = m.end()
    return out


def evaluate(text: str, params: dict[str, Any]) -> float:
    """The value of an OpenSCENARIO expression (the inside of ``${...}``): numbers,
    ``$name`` parameter references, ``+ - * / %``, unary minus and parentheses, with the
    usual precedence; left-associative. A recursive-descent parser of its own (no
    ``eval``); division by zero and non-finite results are errors."""
    toks = _tokens(text)
    if not toks:
        raise ExpressionError("empty expression")
    pos = 0

    def peek() -> tuple[str, Any] | None:
        return toks[pos] if pos < len(toks) else None

    def take() -> tuple[str, Any]:
        nonlocal pos
        tok = toks[pos]
        pos += 1
        return tok

    def primary() -> float:
        tok = peek()
        if tok is None:
            raise ExpressionError("expression ends early")
        if tok == ("op", "-"):
            take()
            return -primary()
        if tok == ("op", "+"):
            take()
            return primary()
        if tok == ("op", "("):
            take()
            v = additive()
            if peek() != ("op", ")"):
                raise ExpressionError("missing ')'")
            take()
            return v
        kind, val = take()
        if kind == "num":
            return val
        if kind == "ref":
            if val not in params:
                raise ExpressionError(f"unknown parameter ${val}")
            try:
                return float(params[val])
            except (TypeError, ValueError):
                raise ExpressionError(f"parameter ${val} = {params[val]!r} is not a number"
                                      ) from None
        raise ExpressionError(f"unexpected {val!r}")

    def term() -> float:
        v = primary()
        while peek() in (("op", "*"), ("op", "/"), ("op", "%")):
            op = take()[1]
            r = primary()
            if op == "*":
                v *= r
            elif r == 0.0:
                raise ExpressionError("division by zero")
            elif op == "/":
                v /= r
            else:
                v = math.fmod(v, r)
        return v

    def additive() -> float:
        v = term()
        while peek() in (("op", "+"), ("op", "-")):
            op = take()[1]
            r = term()
            v = v + r if op == "+" else v - r
        return v

    value = additive()
    if pos != len(toks):
        raise ExpressionError(f"unexpected {toks[pos][1]!r} after the expression")
    if not math.isfinite(value):
        raise ExpressionError("the value is not finite")
    return value


NUMBER_TYPES = ("double", "integer", "unsignedInt", "unsignedShort")
"""The ``parameterType`` values that hold a number."""


def override_text(kind: str, value: Any) -> str:
    """A value given for a declared parameter of type ``kind`` from outside the file (a
    sweep, esmini's ``--param NAME=VALUE``) as the declaration's ``value`` text; a value of
    the wrong type is a ``ValueError`` saying what was expected. A number for a number
    type (integral for an integer type, not negative for an unsigned one), true or false
    for a boolean, a string for any other type (a string is not a number: a sweep's
    ``"10"`` is refused for a double)."""
    if kind in NUMBER_TYPES:
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not math.isfinite(value):
            raise ValueError(f"expected a finite number (parameterType {kind}), got "
                             f"{value!r}")
        if kind != "double" and (value != int(value) or (kind != "integer" and value < 0)):
            raise ValueError(f"expected {'an' if kind == 'integer' else 'a non-negative'} "
                             f"integer (parameterType {kind}), got {value!r}")
        return repr(float(value)) if kind == "double" else str(int(value))
    if kind == "boolean":
        if not isinstance(value, bool):
            raise ValueError(f"expected true or false (parameterType boolean), got {value!r}")
        return "true" if value else "false"
    if not isinstance(value, str):
        raise ValueError(f"expected a string (parameterType {kind}), got {value!r}")
    return value


class Params:
    """Parameter scopes: the file's, then a story's, a catalog entry's, ... (inner first)."""

    def __init__(self, values: dict[str, Any] | None = None,
                 outer: Params | None = None) -> None:
        self.values = dict(values or {})
        self.outer = outer
        self.types: dict[str, str] = {}  # parameterType by name, of this scope's declarations

    def flat(self) -> dict[str, Any]:
        out = self.outer.flat() if self.outer is not None else {}
        out.update(self.values)
        return out

    def resolve(self, node: Node, key: str, raw: str) -> str:
        """An attribute's value with ``$name`` and ``${expr}`` replaced."""
        if not raw.startswith("$"):
            return raw
        flat = self.flat()
        if raw.startswith("${"):
            if not raw.endswith("}"):
                raise node.fail(f"attribute {key!r}: expression {raw!r} has no closing '}}'")
            try:
                v = evaluate(raw[2:-1], flat)
            except ExpressionError as exc:
                raise node.fail(f"attribute {key!r}: bad expression {raw!r}: {exc}") from None
            return repr(v)
        name = raw[1:]
        if name not in flat:
            raise node.fail(f"attribute {key!r}: unknown parameter {raw!r}")
        return str(flat[name])

    def declare(self, decls: Node | None, overrides: dict[str, Any] | None = None) -> Params:
        """A new inner scope from a ``<ParameterDeclarations>`` (values may refer to the
        parameters declared before them); ``overrides`` (name -> value, as esmini's
        ``--param``) replace declared values before anything refers to them
        (:func:`override_text`). Each parameter's type is kept in :attr:`types`."""
        scope = Params({}, self)
        if decls is None:
            return scope
        for d in decls.children:
            if d.tag != "ParameterDeclaration":
                raise d.fail("expected <ParameterDeclaration>")
            name = d.attrs.get("name")
            if not name:
                raise d.fail("missing attribute 'name'")
            kind = d.attrs.get("parameterType", "string")
            scope.types[name] = kind
            if overrides is not None and name in overrides:
                try:
                    raw = override_text(kind, overrides[name])
                except ValueError as exc:
                    raise d.fail(f"parameter {name!r}: override: {exc}") from None
            else:
                raw = scope.resolve(d, "value", d.attrs.get("value", ""))
            if kind in NUMBER_TYPES:
                try:
                    scope.values[name] = float(raw)
                except ValueError:
                    raise d.fail(f"parameter {name!r} of type {kind}: {raw!r} is not a "
                                 "number") from None
            elif kind == "boolean":
                scope.values[name] = raw
            else:
                scope.values[name] = raw
        return scope


# ------------------------------------------------------------------------- the data model
@dataclass
class Vehicle:
    """A vehicle of the file or of a catalog: what the mapping to a car of ours reads."""

    name: str
    category: str
    line: int
    path: Path
    bbox_center_m: tuple[float, float, float]
    bbox_size_m: tuple[float, float, float]  # length, width, height
    max_speed_mps: float
    max_accel_mps2: float
    max_decel_mps2: float
    wheelbase_m: float
    track_m: float
    wheel_diameter_m: float
    max_steering_rad: float
    rear_axle_x_m: float  # the rear axle's x in the vehicle's frame (the reference point)


@dataclass
class Entity:
    name: str
    vehicle: Vehicle
    line: int


@dataclass
class Position:
    """A position element: ``kind`` its tag, ``values`` its attributes resolved (numbers as
    floats, ids as strings), ``orientation`` an ``<Orientation>`` if any."""

    kind: str
    values: dict[str, Any]
    line: int
    orientation: dict[str, Any] | None = None


@dataclass
class Dynamics:
    """A transition: shape (step, linear, cubic, sinusoidal), dimension (time, rate,
    distance) and its value."""

    shape: str
    dimension: str
    value: float


@dataclass
class Action:
    """A private action on one or more actors: ``kind`` one of ``SpeedAction``,
    ``LaneChangeAction``, ``LaneOffsetAction``, ``TeleportAction``."""

    kind: str
    name: str
    line: int
    actors: tuple[str, ...] = ()
    dynamics: Dynamics | None = None
    target: dict[str, Any] = field(default_factory=dict)
    position: Position | None = None


@dataclass
class Condition:
    """One condition: ``kind`` its element's tag (``SimulationTimeCondition``, ...),
    ``values`` its attributes resolved; by-entity conditions have triggering entities."""

    name: str
    kind: str
    line: int
    delay_s: float
    edge: str
    values: dict[str, Any]
    triggering: tuple[str, ...] = ()
    triggering_rule: str = "any"
    position: Position | None = None


Trigger = list[list[Condition]]
"""A trigger: OR over condition groups, each an AND over its conditions ([] : none)."""


@dataclass
class Event:
    name: str
    line: int
    priority: str
    max_executions: int
    actions: list[Action]
    start: Trigger


@dataclass
class Maneuver:
    name: str
    line: int
    events: list[Event]


@dataclass
class ManeuverGroup:
    name: str
    line: int
    max_executions: int
    actors: tuple[str, ...]
    maneuvers: list[Maneuver]


@dataclass
class Act:
    name: str
    line: int
    groups: list[ManeuverGroup]
    start: Trigger
    stop: Trigger


@dataclass
class Story:
    name: str
    line: int
    acts: list[Act]


@dataclass
class Scenario:
    """A read ``.xosc``: header, road file, entities (file order), init actions per
    entity, the stories and the storyboard's stop trigger; ``ignored``: one line per
    element outside the subset that was ignored (the rule in the module docstring)."""

    path: Path
    description: str
    rev: tuple[int, int]
    road_file: Path | None
    entities: dict[str, Entity]
    init: dict[str, list[Action]]
    stories: list[Story]
    stop: Trigger
    parameters: dict[str, Any]
    ignored: tuple[str, ...] = ()
    parameter_types: dict[str, str] = field(default_factory=dict)  # the file's, by name


# ----------------------------------------------------------------------- what is read
IGNORED = {
    "SceneGraphFile": "the scene graph (3-D model) is not used: the road is drawn from the "
                      "OpenDRIVE file",
    "Properties": "vehicle properties (colour, model scaling) do not change the car",
    "TrailerHitch": "trailers are not modelled",
    "Trailer": "trailers are not modelled",
    "ObjectController": "only the default controller: the built-in driver drives the car",
    "TrafficSignals": "traffic signals are not modelled",
    "EnvironmentAction": "the environment (time of day, weather, friction) is not applied",
    "VisibilityAction": "visibility to sensors is not modelled",
    "UsedArea": "the used area is not needed",
}
"""Elements outside the subset that do not move a car: ignored with a warning."""

REFUSED_NOTES = {
    "Pedestrian": "pedestrians are not modelled",
    "MiscObject": "objects are not modelled",
    "RoutingAction": "routes are not supported",
    "FollowTrajectoryAction": "trajectories are not supported",
    "AssignControllerAction": "controllers other than the default are not supported",
    "ActivateControllerAction": "controllers other than the default are not supported",
}

CONDITIONS = {
    # tag: (by entity?, attributes that are numbers, attributes that are strings)
    "SimulationTimeCondition": (False, ("value",), ("rule",)),
    "StoryboardElementStateCondition": (False, (), ("storyboardElementType",
                                                   "storyboardElementRef", "state")),
    "TimeHeadwayCondition": (True, ("value",), ("entityRef", "rule", "freespace",
                                                "alongRoute", "relativeDistanceType",
                                                "coordinateSystem")),
    "TimeToCollisionCondition": (True, ("value",), ("rule", "freespace", "alongRoute",
                                                    "relativeDistanceType",
                                                    "coordinateSystem")),
    "RelativeDistanceCondition": (True, ("value",), ("entityRef", "rule", "freespace",
                                                     "relativeDistanceType",
                                                     "coordinateSystem")),
    "RelativeSpeedCondition": (True, ("value",), ("entityRef", "rule")),
    "SpeedCondition": (True, ("value",), ("rule", "direction")),
    "ReachPositionCondition": (True, ("tolerance",), ()),
    "TraveledDistanceCondition": (True, ("value",), ()),
    "AccelerationCondition": (True, ("value",), ("rule", "direction")),
    "StandStillCondition": (True, ("duration",), ()),
    "CollisionCondition": (True, (), ()),  # its target: <EntityRef> or <ByType>
}
"""The conditions of the subset (docs/openscenario.md has what each measures)."""

COLLISION_TYPES = ("vehicle", "pedestrian", "miscellaneous")
"""``CollisionCondition``'s ``ByType objectType`` values (only vehicles are in the world: a
collision with the others never happens)."""
RULES = ("greaterThan", "lessThan", "equalTo", "greaterOrEqual", "lessOrEqual", "notEqualTo")
EDGES = ("rising", "falling", "risingOrFalling", "none")
SHAPES = ("step", "linear", "cubic", "sinusoidal")
DIMENSIONS = ("time", "rate", "distance")
PRIORITIES = ("overwrite", "override", "skip", "parallel")
ELEMENT_TYPES = ("story", "act", "maneuverGroup", "maneuver", "event", "action")
"""``StoryboardElementStateCondition``'s ``storyboardElementType`` values."""
DISTANCE_TYPES = ("longitudinal", "lateral", "cartesianDistance", "euclidianDistance")
"""``relativeDistanceType`` values (1.0's ``cartesianDistance`` is 1.1's euclidian one)."""
COORDINATE_SYSTEMS = ("entity", "lane", "road")
"""``coordinateSystem`` values measured (along the road: on the roads of the subset the
three agree within a car's heading error); ``trajectory`` is refused."""
BOOLEANS = {"true": "true", "1": "true", "false": "false", "0": "false"}
"""xsd:boolean's four spellings, normalised to ``true``/``false``."""
STATES = ("startTransition", "endTransition", "stopTransition", "skipTransition",
          "completeState", "runningState", "standbyState")
POSITIONS = {
    "WorldPosition": (("x", "y", "z", "h", "p", "r"), ()),
    "LanePosition": (("s", "offset"), ("roadId", "laneId")),
    "RelativeLanePosition": (("ds", "dsLane", "dLane", "offset"), ("entityRef",)),
    "RoadPosition": (("s", "t"), ("roadId",)),
    "RelativeRoadPosition": (("ds", "dt"), ("entityRef",)),
}
"""Position kinds of the subset: (number attributes, string attributes)."""


class _Reader:
    def __init__(self, path: Path, overrides: dict[str, Any] | None = None) -> None:
        self.path = path
        self.overrides = overrides
        self.ignored: dict[str, list[tuple[Path, int]]] = {}
        self.catalog_dirs: dict[str, list[Path]] = {}
        self.catalog_cache: dict[Path, Node] = {}
        self.entity_names: set[str] = set()
        # (condition, element type, name) of every StoryboardElementStateCondition: the
        # names are checked once the whole storyboard is read (a reference may point ahead)
        self.element_refs: list[tuple[Node, str, str]] = []

    # -------------------------------------------------------------- helpers
    def ignore(self, node: Node) -> None:
        self.ignored.setdefault(node.tag, []).append((node.path, node.line))

    def refuse(self, node: Node, what: str = "element") -> XoscError:
        note = REFUSED_NOTES.get(node.tag, "not in the subset simserver plays "
                                           "(docs/openscenario.md)")
        return node.fail(f"{what} outside the subset refused: {note}")

    def num(self, node: Node, p: Params, key: str, default: float | None = None) -> float:
        raw = node.attrs.get(key)
        if raw is None:
            if default is None:
                raise node.fail(f"missing attribute {key!r}")
            return default
        text = p.resolve(node, key, raw)
        try:
            v = float(text)
        except ValueError:
            raise node.fail(f"attribute {key!r}: {text!r} is not a number") from None
        if not math.isfinite(v):
            raise node.fail(f"attribute {key!r}: {text!r} is not finite")
        return v

    def text(self, node: Node, p: Params, key: str, default: str | None = None,
             choices: tuple[str, ...] | None = None) -> str:
        raw = node.attrs.get(key)
        if raw is None:
            if default is None:
                raise node.fail(f"missing attribute {key!r}")
            return default
        v = p.resolve(node, key, raw)
        if choices is not None and v not in choices:
            raise node.fail(f"attribute {key!r}: {v!r} is not one of {', '.join(choices)}")
        return v

    def flag(self, node: Node, p: Params, key: str, default: str = "false") -> str:
        """A boolean attribute as ``"true"`` or ``"false"`` (xsd:boolean: also 1 and 0);
        anything else is an error, not a silent false."""
        v = self.text(node, p, key, default)
        if v not in BOOLEANS:
            raise node.fail(f"attribute {key!r}: {v!r} is not a boolean (true, false, 1, 0)")
        return BOOLEANS[v]

    def entity_ref(self, node: Node, p: Params, key: str = "entityRef") -> str:
        name = self.text(node, p, key)
        if name not in self.entity_names:
            raise node.fail(f"attribute {key!r}: unknown entity {name!r} (entities: "
                            f"{', '.join(sorted(self.entity_names)) or 'none'})")
        return name

    # -------------------------------------------------------------- vehicles and catalogs
    def vehicle(self, node: Node, p: Params) -> Vehicle:
        p = p.declare(node.child("ParameterDeclarations", required=False))
        for c in node.children:
            if c.tag in IGNORED:
                self.ignore(c)
            elif c.tag not in ("ParameterDeclarations", "BoundingBox", "Performance",
                               "Axles"):
                self.ignore(c)
        bb = node.child("BoundingBox")
        center = bb.child("Center")
        dims = bb.child("Dimensions")
        perf = node.child("Performance")
        axles = node.child("Axles")
        front, rear = axles.child("FrontAxle"), axles.child("RearAxle")
        wheelbase = self.num(front, p, "positionX") - self.num(rear, p, "positionX")
        if wheelbase <= 0.0:
            raise front.fail("the front axle must be ahead of the rear axle (positionX)")
        return Vehicle(
            name=self.text(node, p, "name"), category=self.text(node, p, "vehicleCategory",
                                                                 "car"),
            line=node.line, path=node.path,
            bbox_center_m=tuple(self.num(center, p, k) for k in ("x", "y", "z")),
            bbox_size_m=tuple(self.num(dims, p, k) for k in ("length", "width", "height")),
            max_speed_mps=self.num(perf, p, "maxSpeed"),
            max_accel_mps2=self.num(perf, p, "maxAcceleration"),
            max_decel_mps2=self.num(perf, p, "maxDeceleration"),
            wheelbase_m=wheelbase, track_m=self.num(front, p, "trackWidth"),
            wheel_diameter_m=self.num(front, p, "wheelDiameter"),
            max_steering_rad=self.num(front, p, "maxSteering"),
            rear_axle_x_m=self.num(rear, p, "positionX"))

    def catalog_entry(self, ref: Node, p: Params) -> Vehicle:
        catalog = self.text(ref, p, "catalogName")
        entry = self.text(ref, p, "entryName")
        dirs = self.catalog_dirs.get("VehicleCatalog", [])
        if not dirs:
            raise ref.fail(f"catalog {catalog!r}: no <VehicleCatalog> directory in "
                           "<CatalogLocations>")
        for d in dirs:
            for f in sorted(d.glob("*.xosc")):
                root = self.catalog_cache.get(f)
                if root is None:
                    root = self.catalog_cache[f] = read_tree(f)
                cat = root.child("Catalog", required=False)
                if cat is None or cat.attrs.get("name") != catalog:
                    continue
                for v in cat.all("Vehicle"):
                    if v.attrs.get("name") == entry:
                        scope = Params({}, p)
                        for a in ref.all("ParameterAssignments"):
                            for pa in a.all("ParameterAssignment"):
                                scope.values[self.text(pa, p, "parameterRef")] = \
                                    self.text(pa, p, "value")
                        # assignments override the entry's own declared defaults
                        veh = self.vehicle_with(v, scope)
                        return veh
                other = [c for c in cat.children if c.attrs.get("name") == entry]
                if other:
                    raise self.refuse(other[0], "catalog entry")
        raise ref.fail(f"catalog {catalog!r} has no entry {entry!r} (looked in "
                       f"{', '.join(str(d) for d in dirs)})")

    def vehicle_with(self, node: Node, assigned: Params) -> Vehicle:
        """A catalog vehicle whose declared parameters are overridden by assignments."""
        if not assigned.values:
            return self.vehicle(node, Params())
        decls = node.child("ParameterDeclarations", required=False)
        base = Params().declare(decls)
        base.values.update(assigned.values)
        stripped = Node(node.tag, node.attrs, node.line, node.path,
                        [c for c in node.children if c.tag != "ParameterDeclarations"])
        return self.vehicle(stripped, base)

    # -------------------------------------------------------------- positions
    def position(self, node: Node, p: Params) -> Position:
        if node.tag != "Position":
            raise node.fail("expected <Position>")
        kind = node.only_child()
        if kind.tag not in POSITIONS:
            raise self.refuse(kind, "position")
        nums, texts = POSITIONS[kind.tag]
        values: dict[str, Any] = {}
        for k in nums:
            if k in kind.attrs:
                values[k] = self.num(kind, p, k)
        for k in texts:
            if k == "entityRef":
                values[k] = self.entity_ref(kind, p)
            else:
                values[k] = self.text(kind, p, k)
        required = {"WorldPosition": ("x", "y"), "LanePosition": ("s", "roadId", "laneId"),
                    "RelativeLanePosition": ("dLane",), "RoadPosition": ("s", "t", "roadId"),
                    "RelativeRoadPosition": ("ds", "dt")}[kind.tag]
        for k in required:
            if k not in values:
                raise kind.fail(f"missing attribute {k!r}")
        if kind.tag == "LanePosition":
            try:
                values["laneId"] = int(float(values["laneId"]))
            except ValueError:
                raise kind.fail(f"attribute 'laneId': {values['laneId']!r} is not an "
                                "integer") from None
        orient = None
        o = kind.child("Orientation", required=False)
        if o is not None:
            orient = {"type": self.text(o, p, "type", "absolute", ("absolute", "relative")),
                      **{k: self.num(o, p, k, 0.0) for k in ("h", "p", "r")}}
        return Position(kind.tag, values, kind.line, orient)

    # -------------------------------------------------------------- actions
    def dynamics(self, node: Node, p: Params) -> Dynamics:
        return Dynamics(self.text(node, p, "dynamicsShape", choices=SHAPES),
                        self.text(node, p, "dynamicsDimension", choices=DIMENSIONS),
                        self.num(node, p, "value"))

    def private_action(self, node: Node, p: Params, name: str, actors: tuple[str, ...]
                       ) -> Action | None:
        if node.tag != "PrivateAction":
            raise self.refuse(node, "action")
        kind = node.only_child()
        if kind.tag in IGNORED:
            self.ignore(kind)
            return None
        if kind.tag == "TeleportAction":
            return Action("TeleportAction", name, kind.line, actors,
                          position=self.position(kind.child("Position"), p))
        if kind.tag == "LongitudinalAction":
            sa = kind.only_child()
            if sa.tag != "SpeedAction":
                raise self.refuse(sa, "action")
            dyn = self.dynamics(sa.child("SpeedActionDynamics"), p)
            tgt = sa.child("SpeedActionTarget").only_child()
            if tgt.tag == "AbsoluteTargetSpeed":
                target = {"kind": "absolute", "value": self.num(tgt, p, "value")}
            elif tgt.tag == "RelativeTargetSpeed":
                target = {"kind": "relative", "entityRef": self.entity_ref(tgt, p),
                          "value": self.num(tgt, p, "value"),
                          "valueType": self.text(tgt, p, "speedTargetValueType", "delta",
                                                 ("delta", "factor")),
                          "continuous": self.flag(tgt, p, "continuous") == "true"}
            else:
                raise self.refuse(tgt, "speed target")
            return Action("SpeedAction", name, sa.line, actors, dyn, target)
        if kind.tag == "LateralAction":
            la = kind.only_child()
            if la.tag == "LaneChangeAction":
                dyn = self.dynamics(la.child("LaneChangeActionDynamics"), p)
                tgt = la.child("LaneChangeTarget").only_child()
                if tgt.tag == "AbsoluteTargetLane":
                    target = {"kind": "absolute", "value": int(self.num(tgt, p, "value"))}
                elif tgt.tag == "RelativeTargetLane":
                    target = {"kind": "relative", "entityRef": self.entity_ref(tgt, p),
                              "value": int(self.num(tgt, p, "value"))}
                else:
                    raise self.refuse(tgt, "lane target")
                target["offset"] = self.num(la, p, "targetLaneOffset", 0.0)
                return Action("LaneChangeAction", name, la.line, actors, dyn, target)
            if la.tag == "LaneOffsetAction":
                d = la.child("LaneOffsetActionDynamics")
                dyn = Dynamics(self.text(d, p, "dynamicsShape", choices=SHAPES), "rate",
                               self.num(d, p, "maxLateralAcc", math.inf))
                tgt = la.child("LaneOffsetTarget").only_child()
                if tgt.tag == "AbsoluteTargetLaneOffset":
                    target = {"kind": "absolute", "value": self.num(tgt, p, "value")}
                elif tgt.tag == "RelativeTargetLaneOffset":
                    target = {"kind": "relative", "entityRef": self.entity_ref(tgt, p),
                              "value": self.num(tgt, p, "value")}
                else:
                    raise self.refuse(tgt, "lane offset target")
                target["continuous"] = self.flag(la, p, "continuous") == "true"
                return Action("LaneOffsetAction", name, la.line, actors, dyn, target)
            raise self.refuse(la, "action")
        raise self.refuse(kind, "action")

    # -------------------------------------------------------------- triggers
    def trigger(self, node: Node | None, p: Params) -> Trigger:
        if node is None:
            return []
        groups = []
        for g in node.children:
            if g.tag != "ConditionGroup":
                raise g.fail("expected <ConditionGroup>")
            conds = [self.condition(c, p) for c in g.children]
            if not conds:
                raise g.fail("a condition group needs at least one <Condition>")
            groups.append(conds)
        return groups

    def condition(self, node: Node, p: Params) -> Condition:
        if node.tag != "Condition":
            raise node.fail("expected <Condition>")
        name = self.text(node, p, "name", "")
        delay = self.num(node, p, "delay", 0.0)
        if delay < 0.0:
            raise node.fail("attribute 'delay' must be >= 0")
        edge = self.text(node, p, "conditionEdge", "none", EDGES)
        by = node.only_child()
        triggering: tuple[str, ...] = ()
        rule = "any"
        if by.tag == "ByEntityCondition":
            te = by.child("TriggeringEntities")
            rule = self.text(te, p, "triggeringEntitiesRule", "any", ("any", "all"))
            triggering = tuple(self.entity_ref(e, p) for e in te.all("EntityRef"))
            if not triggering:
                raise te.fail("no <EntityRef>")
            inner = by.child("EntityCondition").only_child()
        elif by.tag == "ByValueCondition":
            inner = by.only_child()
        else:
            raise self.refuse(by, "condition")
        spec = CONDITIONS.get(inner.tag)
        if spec is None or spec[0] != (by.tag == "ByEntityCondition"):
            raise self.refuse(inner, "condition")
        _, nums, texts = spec
        values: dict[str, Any] = {}
        for k in nums:
            values[k] = self.num(inner, p, k, 0.0 if k == "duration" else None)
        for k in texts:
            if k in inner.attrs:
                values[k] = (self.entity_ref(inner, p) if k == "entityRef"
                             else self.flag(inner, p, k) if k in ("freespace", "alongRoute")
                             else self.text(inner, p, k))
        self._check_measure(inner, values)
        if "rule" in texts and "rule" not in values:
            raise inner.fail("missing attribute 'rule'")
        if values.get("rule") is not None and values["rule"] not in RULES:
            raise inner.fail(f"attribute 'rule': {values['rule']!r} is not one of "
                             f"{', '.join(RULES)}")
        if "entityRef" in texts and inner.tag != "TimeToCollisionCondition" \
                and "entityRef" not in values:
            raise inner.fail("missing attribute 'entityRef'")
        position = None
        if inner.tag == "TimeToCollisionCondition":
            tgt = inner.child("TimeToCollisionConditionTarget").only_child()
            if tgt.tag == "EntityRef":
                values["entityRef"] = self.entity_ref(tgt, p)
            else:
                raise self.refuse(tgt, "time-to-collision target")
        if inner.tag == "CollisionCondition":  # with one entity, or any of a type
            tgt = inner.only_child()
            if tgt.tag == "EntityRef":
                values["entityRef"] = self.entity_ref(tgt, p)
            elif tgt.tag == "ByType":
                values["objectType"] = self.text(tgt, p, "objectType", None,
                                                 COLLISION_TYPES)
            else:
                raise self.refuse(tgt, "collision target")
        if inner.tag == "ReachPositionCondition":
            position = self.position(inner.child("Position"), p)
        if inner.tag == "StoryboardElementStateCondition":
            for key, allowed in (("state", STATES), ("storyboardElementType", ELEMENT_TYPES)):
                if values.get(key) not in allowed:
                    raise inner.fail(f"attribute {key!r}: {values.get(key)!r} is not one of "
                                     f"{', '.join(allowed)}")
            self.element_refs.append((inner, values["storyboardElementType"],
                                      values["storyboardElementRef"]))
        return Condition(name, inner.tag, inner.line, delay, edge, values, triggering, rule,
                         position)

    def _check_measure(self, inner: Node, values: dict[str, Any]) -> None:
        """The distance a condition measures, within what the player measures: an unknown
        ``relativeDistanceType`` or ``coordinateSystem`` is an error (a typo would else
        measure another distance), one outside the subset is refused (docs/openscenario.md:
        the longitudinal distance along the road for headway and time to collision;
        freespace only longitudinally)."""
        kind = values.get("relativeDistanceType")
        if kind is not None and kind not in DISTANCE_TYPES:
            raise inner.fail(f"attribute 'relativeDistanceType': {kind!r} is not one of "
                             f"{', '.join(DISTANCE_TYPES)}")
        system = values.get("coordinateSystem")
        if system is not None and system not in COORDINATE_SYSTEMS + ("trajectory",):
            raise inner.fail(f"attribute 'coordinateSystem': {system!r} is not one of "
                             f"{', '.join(COORDINATE_SYSTEMS + ('trajectory',))}")
        if system == "trajectory":
            raise inner.fail("coordinateSystem 'trajectory' outside the subset refused: "
                             "trajectories are not supported")
        if kind not in (None, "longitudinal") and inner.tag in ("TimeHeadwayCondition",
                                                               "TimeToCollisionCondition"):
            raise inner.fail(f"relativeDistanceType {kind!r} outside the subset refused: "
                             "headway and time to collision are measured longitudinally")
        if kind not in (None, "longitudinal") and values.get("freespace") == "true":
            raise inner.fail(f"freespace distance {kind!r} outside the subset refused: "
                             "freespace is measured longitudinally (bumper to bumper)")

    # -------------------------------------------------------------- the storyboard
    def max_exec(self, node: Node, p: Params) -> int:
        v = self.num(node, p, "maximumExecutionCount", 1.0)
        if v < 1 or v != int(v):
            raise node.fail("attribute 'maximumExecutionCount' must be a whole number >= 1")
        return int(v)

    def only_known_children(self, node: Node, known: tuple[str, ...]) -> None:
        """A storyboard element's children are those of the schema the subset reads; any
        other child is refused by name and line (a misspelt ``<Maneuvr>`` would else be
        dropped silently, and the scenario played without it)."""
        for c in node.children:
            if c.tag not in known:
                raise self.refuse(c)

    def story(self, node: Node, p: Params) -> Story:
        self.only_known_children(node, ("ParameterDeclarations", "Act"))
        p = p.declare(node.child("ParameterDeclarations", required=False))
        acts = []
        for a in node.all("Act"):
            self.only_known_children(a, ("ManeuverGroup", "StartTrigger", "StopTrigger"))
            groups = []
            for g in a.all("ManeuverGroup"):
                self.only_known_children(g, ("Actors", "Maneuver", "CatalogReference"))
                actors_node = g.child("Actors")
                if self.flag(actors_node, p, "selectTriggeringEntities") == "true":
                    raise actors_node.fail("selectTriggeringEntities 'true' outside the "
                                           "subset refused: the actors are the entities "
                                           "named in <Actors>")
                self.only_known_children(actors_node, ("EntityRef",))
                actors = tuple(self.entity_ref(e, p) for e in actors_node.all("EntityRef"))
                maneuvers = []
                for m in g.children:
                    if m.tag == "CatalogReference":
                        raise self.refuse(m, "maneuver catalog reference")
                    if m.tag != "Maneuver":
                        continue
                    self.only_known_children(m, ("ParameterDeclarations", "Event"))
                    mp = p.declare(m.child("ParameterDeclarations", required=False))
                    events = []
                    for e in m.all("Event"):
                        self.only_known_children(e, ("Action", "StartTrigger"))
                        actions = []
                        for act in e.all("Action"):
                            inner = act.only_child()
                            if inner.tag != "PrivateAction":
                                if inner.tag == "GlobalAction" and inner.children and \
                                        inner.children[0].tag in IGNORED:
                                    self.ignore(inner.children[0])
                                    continue
                                raise self.refuse(inner, "action")
                            if not actors:
                                raise act.fail("a private action needs actors (<Actors>)")
                            got = self.private_action(inner, mp, act.attrs.get("name", ""),
                                                      actors)
                            if got is not None:
                                actions.append(got)
                        events.append(Event(
                            self.text(e, mp, "name"), e.line,
                            self.text(e, mp, "priority", "overwrite", PRIORITIES),
                            self.max_exec(e, mp), actions,
                            self.trigger(e.child("StartTrigger", required=False), mp)))
                    maneuvers.append(Maneuver(self.text(m, mp, "name"), m.line, events))
                groups.append(ManeuverGroup(self.text(g, p, "name"), g.line,
                                            self.max_exec(g, p), actors, maneuvers))
            acts.append(Act(self.text(a, p, "name"), a.line, groups,
                            self.trigger(a.child("StartTrigger", required=False), p),
                            self.trigger(a.child("StopTrigger", required=False), p)))
        return Story(self.text(node, p, "name"), node.line, acts)

    def read(self) -> Scenario:
        root = read_tree(self.path)
        if root.tag != "OpenSCENARIO":
            raise root.fail("the root element must be <OpenSCENARIO>")
        header = root.child("FileHeader")
        rev = (int(self.num(header, Params(), "revMajor")),
               int(self.num(header, Params(), "revMinor")))
        if rev[0] != 1:
            raise header.fail(f"OpenSCENARIO {rev[0]}.{rev[1]}: only 1.x is read")
        known = ("FileHeader", "ParameterDeclarations", "CatalogLocations", "RoadNetwork",
                 "Entities", "Storyboard")
        for c in root.children:
            if c.tag not in known:
                raise self.refuse(c)
        decls = root.child("ParameterDeclarations", required=False)
        p = Params().declare(decls, self.overrides)
        unknown = sorted(set(self.overrides or ()) - set(p.values))
        if unknown:
            raise (decls or root).fail(
                f"no parameter {unknown[0]!r} is declared to override (declared: "
                f"{', '.join(p.values) or 'none'})")
        locs = root.child("CatalogLocations", required=False)
        for loc in (locs.children if locs is not None else []):
            if loc.tag != "VehicleCatalog":
                self.ignore(loc)  # other catalogs are read only when referenced (refused)
                continue
            d = loc.child("Directory")
            path = (self.path.parent / self.text(d, p, "path")).resolve()
            if not path.is_dir():
                raise d.fail(f"catalog directory {path} does not exist")
            self.catalog_dirs.setdefault("VehicleCatalog", []).append(path)
        road_file = None
        net = root.child("RoadNetwork", required=False)
        if net is not None:
            for c in net.children:
                if c.tag == "LogicFile":
                    fp = self.text(c, p, "filepath")
                    road_file = (self.path.parent / fp).resolve()
                    if not road_file.is_file():
                        raise c.fail(f"road file {fp!r} ({road_file}) does not exist")
                else:
                    self.ignore(c)
        ents = root.child("Entities")
        objects = ents.all("ScenarioObject")
        for c in ents.children:
            if c.tag != "ScenarioObject":
                raise self.refuse(c, "entity")
        self.entity_names = {self.text(o, p, "name") for o in objects}
        entities: dict[str, Entity] = {}
        for o in objects:
            name = self.text(o, p, "name")
            if name in entities:
                raise o.fail(f"entity {name!r} is declared twice")
            body = next((c for c in o.children if c.tag != "ObjectController"), None)
            for c in o.children:
                if c.tag == "ObjectController":
                    self.ignore(c)
            if body is None:
                raise o.fail("no <Vehicle> or <CatalogReference>")
            if body.tag == "Vehicle":
                veh = self.vehicle(body, p)
            elif body.tag == "CatalogReference":
                veh = self.catalog_entry(body, p)
            else:
                raise self.refuse(body, "entity")
            entities[name] = Entity(name, veh, o.line)
        board = root.child("Storyboard")
        init: dict[str, list[Action]] = {name: [] for name in entities}
        init_node = board.child("Init")
        actions = init_node.child("Actions", required=False)
        for c in (actions.children if actions is not None else []):
            if c.tag == "Private":
                ent = self.entity_ref(c, p)
                for pa in c.children:
                    got = self.private_action(pa, p, "", (ent,))
                    if got is not None:
                        if got.kind not in ("TeleportAction", "SpeedAction"):
                            raise c.fail(f"<{got.kind}> in <Init>: only TeleportAction and "
                                         "SpeedAction are read there")
                        init[ent].append(got)
            elif c.tag == "GlobalAction" and c.children and c.children[0].tag in IGNORED:
                self.ignore(c.children[0])
            else:
                raise self.refuse(c, "init action")
        stories = [self.story(s, p) for s in board.all("Story")]
        for c in board.children:
            if c.tag not in ("Init", "Story", "StopTrigger"):
                raise self.refuse(c)
        stop = self.trigger(board.child("StopTrigger", required=False), p)
        self._check_unique_names(stories)
        known = {(kind, name) for kind, name, _ in storyboard_elements(stories)}
        for cond, kind, name in self.element_refs:
            if (kind, name) not in known:
                raise cond.fail(f"attribute 'storyboardElementRef': no {kind} named "
                                f"{name!r} in the storyboard")
        ignored = tuple(
            f"{self.path.name}: <{tag}> ignored, {len(at)} x (at "
            f"{', '.join(f'{pp.name}:{n}' for pp, n in at[:10])}"
            f"{', ...' if len(at) > 10 else ''}): "
            f"{IGNORED.get(tag, 'not in the subset; it does not move a car')}"
            for tag, at in self.ignored.items())
        return Scenario(self.path, header.attrs.get("description", ""), rev, road_file,
                        entities, init, stories, stop, p.flat(), ignored, dict(p.types))

    def _check_unique_names(self, stories: list[Story]) -> None:
        """Storyboard element names are what state conditions refer to: each must be
        unique within its kind, as the conditions look them up by name."""
        seen: dict[tuple[str, str], int] = {}
        for kind, name, line in storyboard_elements(stories):
            if (kind, name) in seen:
                raise XoscError(f"{self.path}:{line}: <{kind}>: name {name!r} is used "
                                f"twice (line {seen[kind, name]}): references by name would "
                                "be ambiguous")
            seen[kind, name] = line


def storyboard_elements(stories: list[Story]) -> list[tuple[str, str, int]]:
    """Every storyboard element as ``(kind, name, line)``, in file order."""
    out = []
    for s in stories:
        out.append(("story", s.name, s.line))
        for a in s.acts:
            out.append(("act", a.name, a.line))
            for g in a.groups:
                out.append(("maneuverGroup", g.name, g.line))
                for m in g.maneuvers:
                    out.append(("maneuver", m.name, m.line))
                    for e in m.events:
                        out.append(("event", e.name, e.line))
                        for act in e.actions:
                            if act.name:
                                out.append(("action", act.name, act.line))
    return out


def load_openscenario(path: str | Path, parameters: dict[str, Any] | None = None) -> Scenario:
    """Read an OpenSCENARIO 1.x file of the subset (errors: :class:`XoscError`).
    ``parameters``: values for some of the file's own ``<ParameterDeclarations>`` (by
    name, :func:`override_text`), set before any expression is evaluated, as esmini's
    ``--param``; a name the file does not declare is an error."""
    return _Reader(Path(path), parameters).read()
