"""Named light-transport effects of the virtual rig, switched on by name.

Every effect is a setting of :class:`~slscan.virtual.render.Optics` (light between the
projector, the scene and the lens) or of :class:`~slscan.virtual.sensor.Sensor` (what the
camera does with the light), so it can also be set key by key in a recipe's
``[capture.optics]`` / ``[capture.sensor]`` tables. A name here is the short way: it
turns the effect on at the typical values its fields default to, and leaves any value a
user already set alone, so applying an effect twice changes nothing.

    slscan capture --effects interreflection,dof --out scan
    [capture]
    effects = ["all"]

Materials (matte, marble, bronze) belong to the scene (:mod:`slscan.virtual.scenes`); the
``subsurface`` effect decides whether the scene's materials carry light under the surface.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

from slscan.errors import SlscanError

Apply = Callable[["object", "object", float], "tuple[object, object]"]


@dataclass(frozen=True)
class Effect:
    """One switchable effect.

    name : what ``--effects`` and ``capture.effects`` call it
    summary : one line: what it models
    reference : where the model comes from
    apply : ``(optics, sensor, working_distance_mm) -> (optics, sensor)`` with the effect on
    """

    name: str
    summary: str
    reference: str
    apply: Apply


EFFECTS: dict[str, Effect] = {}


def register(effect: Effect) -> Effect:
    """Add ``effect`` to :data:`EFFECTS` (names are unique)."""
    if effect.name in EFFECTS or effect.name in ("all", "none"):
        raise ValueError(f"effect {effect.name!r} is already registered")
    EFFECTS[effect.name] = effect
    return effect


def _load() -> dict[str, Effect]:
    # the modules that own the effects register them when imported
    import slscan.virtual.render
    import slscan.virtual.sensor  # noqa: F401

    return EFFECTS


def parse_effects(value: str | Iterable[str] | None, where: str = "effects") -> tuple[str, ...]:
    """Effect names in registry order from ``"a,b"``, a list, ``"all"`` or ``"none"``.

    Unknown names are refused naming ``where`` and listing the known ones."""
    known = _load()
    if value is None:
        return ()
    items = value.split(",") if isinstance(value, str) else list(value)
    names: set[str] = set()
    for item in items:
        if not isinstance(item, str):
            raise SlscanError(f"{where}: expected effect names, got {item!r}")
        name = item.strip()
        if name in ("", "none"):
            continue
        if name == "all":
            names.update(known)
        elif name in known:
            names.add(name)
        else:
            raise SlscanError(f"{where}: unknown effect {name!r} (known: all, none, {', '.join(known)})")
    return tuple(n for n in known if n in names)


def apply_effects(names: Iterable[str], optics, sensor, working_distance: float):
    """``(optics, sensor)`` with the named effects switched on."""
    known = _load()
    for name in names:
        optics, sensor = known[name].apply(optics, sensor, working_distance)
    return optics, sensor


def describe() -> list[tuple[str, str, str]]:
    """(name, summary, reference) of every effect, for help texts and docs."""
    return [(e.name, e.summary, e.reference) for e in _load().values()]
