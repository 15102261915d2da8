"""UAVTalk object definitions, read from LibrePilot 16.09's XMLs (``dialects/uavtalk/``).

An :class:`ObjectDef` is one UAVObject: its name, the 32-bit id the GCS and the firmware derive
from the definition, its fields in *wire* order and a ``struct`` packer for its data.  The parsing
follows 16.09's ``ground/uavobjgenerator/uavobjectparser.cpp``:

- a field's element count comes from ``elementnames`` (attribute or child list) before
  ``elements``; enum ``options`` likewise (attribute, else child ``<options><option>``);
- ``cloneof`` copies an *earlier declared* field of the same object, only the name differs;
- ``defaultvalue`` is comma separated, one per element, or one for all (the legacy form); enum
  defaults are option names; a missing default is 0 (the first option for an enum);
- the fields are stable-sorted by element size, descending (enum counts as 1 byte): that order
  is both the wire order and the hash order.

The id hash (shift-add-xor, u32): name bytes (signed chars), is_settings, single_instance, then
per field its name bytes, element count, type index and, for enums, every option's bytes;
``id = hash & 0xFFFFFFFE``, the metaobject's id is ``id + 1``.

A metaobject's data is 16.09's ``UAVObjMetadata`` (``flight/uavobjects/inc/uavobjectmanager.h``,
the GCS's ``UAVObject::Metadata``): ``flags`` u16 then three u16 periods (flight telemetry, GCS
telemetry, logging), 8 bytes.  :class:`MetaDef` packs it; :meth:`Telemetry.metadata` builds its
default values from an object's ``access``/``telemetryflight``/``telemetrygcs``/``logging``
elements as the flight generator's ``uavobject.c.template`` does.

All 113 XMLs of 16.09 are kept: a GCS may request any of them.  Parsing them takes ~12 ms, once
per process (:meth:`ObjectSet.load` caches the default set, read as package resources).
"""

from __future__ import annotations

import functools
import struct
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Mapping
from enum import IntEnum
from importlib import resources
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import Any, NamedTuple

__all__ = [
    "META_SIZE",
    "AccessMode",
    "FieldDef",
    "MetaDef",
    "ObjectDef",
    "ObjectSet",
    "Telemetry",
    "TelemetrySpec",
    "UpdateMode",
    "object_id",
]

TYPES = ("int8", "int16", "int32", "uint8", "uint16", "uint32", "float", "enum")
"""Field types in the generator's order: the index is what the id hash uses."""
_TYPE_SIZE = {"int8": 1, "int16": 2, "int32": 4, "uint8": 1, "uint16": 2, "uint32": 4,
              "float": 4, "enum": 1}
_TYPE_CODE = {"int8": "b", "int16": "h", "int32": "i", "uint8": "B", "uint16": "H", "uint32": "I",
              "float": "f", "enum": "B"}
_INT_RANGE = {"int8": (-(1 << 7), (1 << 7) - 1), "int16": (-(1 << 15), (1 << 15) - 1),
              "int32": (-(1 << 31), (1 << 31) - 1), "uint8": (0, 0xFF), "uint16": (0, 0xFFFF),
              "uint32": (0, 0xFFFFFFFF), "enum": (0, 0xFF)}

META_SIZE = 8
"""A metaobject's data length in 16.09: flags u16 + 3 × u16 periods (``UAVObjMetadata``)."""

# UAVObjMetadata flag bits (uavobjectmanager.h)
_ACCESS_SHIFT = 0
_GCS_ACCESS_SHIFT = 1
_TELEMETRY_ACKED_SHIFT = 2
_GCS_TELEMETRY_ACKED_SHIFT = 3
_TELEMETRY_UPDATE_MODE_SHIFT = 4
_GCS_TELEMETRY_UPDATE_MODE_SHIFT = 6
_LOGGING_UPDATE_MODE_SHIFT = 8
_UPDATE_MODE_MASK = 0x3


class UpdateMode(IntEnum):
    """How an object is sent (``UAVObjUpdateMode``)."""

    MANUAL = 0
    PERIODIC = 1
    ONCHANGE = 2
    THROTTLED = 3


class AccessMode(IntEnum):
    """Who may write an object (``UAVObjAccessType``)."""

    READWRITE = 0
    READONLY = 1


class TelemetrySpec(NamedTuple):
    """One of the XML's ``telemetryflight``/``telemetrygcs``/``logging`` elements."""

    acked: bool
    update_mode: UpdateMode
    period_ms: int


class Telemetry(NamedTuple):
    """An object's default metadata, as its XML declares it."""

    flight: TelemetrySpec
    gcs: TelemetrySpec
    logging: TelemetrySpec
    flight_access: AccessMode = AccessMode.READWRITE
    gcs_access: AccessMode = AccessMode.READWRITE

    @property
    def flags(self) -> int:
        """The metadata's ``flags`` word."""
        return (
            self.flight_access << _ACCESS_SHIFT
            | self.gcs_access << _GCS_ACCESS_SHIFT
            | int(self.flight.acked) << _TELEMETRY_ACKED_SHIFT
            | int(self.gcs.acked) << _GCS_TELEMETRY_ACKED_SHIFT
            | self.flight.update_mode << _TELEMETRY_UPDATE_MODE_SHIFT
            | self.gcs.update_mode << _GCS_TELEMETRY_UPDATE_MODE_SHIFT
            | self.logging.update_mode << _LOGGING_UPDATE_MODE_SHIFT
        )

    def metadata(self) -> dict[str, int]:
        """The metaobject's values (for :meth:`MetaDef.pack`)."""
        return {
            "Modes": self.flags,
            "FlightTelemetryUpdatePeriod": self.flight.period_ms,
            "GCSTelemetryUpdatePeriod": self.gcs.period_ms,
            "LoggingUpdatePeriod": self.logging.period_ms,
        }

    @classmethod
    def from_metadata(cls, values: Mapping[str, int]) -> Telemetry:
        """Decode a metaobject's values (as :meth:`MetaDef.unpack` returns them)."""
        flags = values["Modes"]

        def mode(shift: int) -> UpdateMode:
            return UpdateMode((flags >> shift) & _UPDATE_MODE_MASK)

        return cls(
            flight=TelemetrySpec(bool(flags >> _TELEMETRY_ACKED_SHIFT & 1),
                                 mode(_TELEMETRY_UPDATE_MODE_SHIFT),
                                 values["FlightTelemetryUpdatePeriod"]),
            gcs=TelemetrySpec(bool(flags >> _GCS_TELEMETRY_ACKED_SHIFT & 1),
                              mode(_GCS_TELEMETRY_UPDATE_MODE_SHIFT),
                              values["GCSTelemetryUpdatePeriod"]),
            logging=TelemetrySpec(False, mode(_LOGGING_UPDATE_MODE_SHIFT),
                                  values["LoggingUpdatePeriod"]),
            flight_access=AccessMode(flags >> _ACCESS_SHIFT & 1),
            gcs_access=AccessMode(flags >> _GCS_ACCESS_SHIFT & 1),
        )


class FieldDef(NamedTuple):
    """One field: ``count`` elements of ``type`` (enum: ``options``), ``defaults`` per element."""

    name: str
    type: str
    count: int  # type: ignore[assignment]  # (shadows tuple.count: the fixed interface)
    options: tuple[str, ...]
    defaults: tuple[Any, ...]
    element_names: tuple[str, ...] = ()

    @property
    def element_size(self) -> int:
        """Bytes per element on the wire."""
        return _TYPE_SIZE[self.type]


# ---------------------------------------------------------------------------------------- hash


def _hash_step(h: int, value: int) -> int:
    return (h ^ (((h << 5) + (h >> 2) + value) & 0xFFFFFFFF)) & 0xFFFFFFFF


def _hash_text(h: int, text: str) -> int:
    for byte in text.encode("latin-1"):
        h = _hash_step(h, byte - 256 if byte > 127 else byte)  # signed char, widened to u32
    return h


def _wire_order(fields: list[FieldDef]) -> tuple[FieldDef, ...]:
    # qStableSort by numBytes, descending (sorted() is stable)
    return tuple(sorted(fields, key=lambda f: -f.element_size))


def object_id(name: str, is_settings: bool, single_instance: bool,
              fields: list[FieldDef] | tuple[FieldDef, ...]) -> int:
    """The object's id, as 16.09's ``UAVObjectParser::calculateID`` computes it.

    ``fields`` may be in declaration order: they are stable-sorted to wire order here.
    """
    h = _hash_text(0, name)
    h = _hash_step(h, int(is_settings))
    h = _hash_step(h, int(single_instance))
    for f in _wire_order(list(fields)):
        h = _hash_text(h, f.name)
        h = _hash_step(h, f.count)
        h = _hash_step(h, TYPES.index(f.type))
        if f.type == "enum":
            for option in f.options:
                h = _hash_text(h, option)
    return h & 0xFFFFFFFE


# ------------------------------------------------------------------------------------- objects


class ObjectDef:
    """One UAVObject definition (immutable); ``pack``/``unpack`` convert its data."""

    __slots__ = (
        "_by_name",
        "_struct",
        "description",
        "fields",
        "id",
        "is_settings",
        "meta_id",
        "name",
        "priority",
        "single_instance",
        "size",
        "telemetry",
    )

    name: str
    id: int
    meta_id: int
    is_settings: bool
    single_instance: bool
    priority: bool
    fields: tuple[FieldDef, ...]
    size: int
    telemetry: Telemetry
    description: str
    _struct: struct.Struct
    _by_name: dict[str, FieldDef]

    def __init__(self, name: str, fields: tuple[FieldDef, ...] | list[FieldDef], *,
                 is_settings: bool = False, single_instance: bool = True,
                 telemetry: Telemetry | None = None, priority: bool = False,
                 description: str = "", object_id_: int | None = None) -> None:
        ordered = _wire_order(list(fields))
        fmt = "<" + "".join(f"{f.count}{_TYPE_CODE[f.type]}" for f in ordered)
        oid = object_id(name, is_settings, single_instance, ordered) if object_id_ is None \
            else object_id_
        manual = TelemetrySpec(False, UpdateMode.MANUAL, 0)
        values = {
            "name": name, "id": oid, "meta_id": oid + 1, "is_settings": is_settings,
            "single_instance": single_instance, "priority": priority, "fields": ordered,
            "telemetry": telemetry or Telemetry(manual, manual, manual),
            "description": description, "_struct": struct.Struct(fmt),
            "_by_name": {f.name: f for f in ordered},
        }
        for key, value in values.items():
            object.__setattr__(self, key, value)
        object.__setattr__(self, "size", self._struct.size)

    def __setattr__(self, key: str, value: Any) -> None:
        raise AttributeError(f"{type(self).__name__} is immutable")

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name} 0x{self.id:08X} {self.size} B>"

    def defaults(self) -> dict[str, Any]:
        """Every field at its XML default (arrays as lists, enums as int)."""
        return {f.name: f.defaults[0] if f.count == 1 else list(f.defaults) for f in self.fields}

    def pack(self, values: Mapping[str, Any]) -> bytes:
        """The object's data; missing fields take their defaults.

        Raises ValueError on an unknown field, a wrong array length, an unknown enum option or
        a value out of its type's range.
        """
        unknown = set(values) - self._by_name.keys()
        if unknown:
            raise ValueError(f"{self.name}: unknown field(s) {sorted(unknown)}")
        flat: list[Any] = []
        for f in self.fields:
            if f.name not in values:
                flat.extend(f.defaults)
                continue
            value = values[f.name]
            items = list(value) if isinstance(value, (list, tuple)) else [value]
            if len(items) != f.count:
                raise ValueError(f"{self.name}.{f.name}: {len(items)} values, {f.count} expected")
            for item in items:
                flat.append(_check(self.name, f, item))
        return self._struct.pack(*flat)

    def unpack(self, data: bytes) -> dict[str, Any]:
        """Field values from the object's data (arrays as lists, enums as int)."""
        if len(data) != self.size:
            raise ValueError(f"{self.name}: {len(data)} bytes, {self.size} expected")
        flat = self._struct.unpack(data)
        out: dict[str, Any] = {}
        i = 0
        for f in self.fields:
            out[f.name] = flat[i] if f.count == 1 else list(flat[i:i + f.count])
            i += f.count
        return out

    def field(self, name: str) -> FieldDef:
        """The field called ``name`` (KeyError naming it)."""
        try:
            return self._by_name[name]
        except KeyError:
            raise KeyError(f"{self.name} has no field {name!r}") from None


def _check(obj: str, f: FieldDef, item: Any) -> Any:
    if f.type == "float":
        if isinstance(item, bool) or not isinstance(item, (int, float)):
            raise ValueError(f"{obj}.{f.name}: {item!r} is not a number")
        return float(item)
    if f.type == "enum" and isinstance(item, str):
        try:
            return f.options.index(item)
        except ValueError:
            raise ValueError(f"{obj}.{f.name}: {item!r} is not one of {list(f.options)}") from None
    if isinstance(item, bool) or not isinstance(item, int):
        raise ValueError(f"{obj}.{f.name}: {item!r} is not an integer")
    low, high = _INT_RANGE[f.type]
    if not low <= item <= high:
        raise ValueError(f"{obj}.{f.name}: {item} outside {f.type} range")
    return item


_META_FIELDS = tuple(
    FieldDef(name, "uint16", 1, (), (0,))
    for name in ("Modes", "FlightTelemetryUpdatePeriod", "GCSTelemetryUpdatePeriod",
                 "LoggingUpdatePeriod")
)


class MetaDef(ObjectDef):
    """The metaobject of ``parent``: its ``UAVObjMetadata`` (id = parent id + 1, 8 bytes).

    Its defaults are the parent's XML telemetry settings (:meth:`Telemetry.metadata`).
    """

    __slots__ = ("parent",)

    parent: ObjectDef

    def __init__(self, parent: ObjectDef) -> None:
        defaults = parent.telemetry.metadata()
        fields = tuple(f._replace(defaults=(defaults[f.name],)) for f in _META_FIELDS)
        super().__init__(f"{parent.name}Meta", fields, is_settings=False, single_instance=True,
                         description=f"Metadata of {parent.name}", object_id_=parent.id + 1)
        object.__setattr__(self, "parent", parent)
        assert self.size == META_SIZE


# -------------------------------------------------------------------------------------- parsing


def _split(text: str) -> list[str]:
    return [part.strip() for part in text.split(",") if part.strip()]


def _child_list(node: ET.Element, outer: str, inner: str) -> list[str]:
    lst = node.find(outer)
    if lst is None:
        return []
    return [e.text for e in lst.findall(inner) if e.text]


def _parse_default(obj: str, field: str, ftype: str, options: list[str], text: str) -> Any:
    if ftype == "enum":
        try:
            return options.index(text)
        except ValueError:
            raise ValueError(f"{obj}.{field}: default {text!r} not an option") from None
    if ftype == "float":
        return struct.unpack("<f", struct.pack("<f", float(text)))[0]  # as the f32 holds it
    try:
        return int(text, 0)
    except ValueError:
        return int(float(text))  # "1.0" in an integer field: the C initialiser truncates


def _parse_field(obj: str, node: ET.Element, declared: list[FieldDef],
                 is_settings: bool) -> FieldDef:
    name = node.get("name")
    if not name:
        raise ValueError(f"{obj}: a field has no name")
    clone = node.get("cloneof")
    if clone is not None:
        for parent in declared:
            if parent.name == clone:
                return parent._replace(name=name)
        raise ValueError(f"{obj}.{name}: cloneof unknown field {clone!r}")
    ftype = node.get("type", "")
    if ftype not in _TYPE_SIZE:
        raise ValueError(f"{obj}.{name}: unknown type {ftype!r}")
    attr = node.get("elementnames")
    names = _split(attr) if attr is not None else _child_list(node, "elementnames", "elementname")
    count = len(names) if names else int(node.get("elements", "0"))
    if count <= 0:
        raise ValueError(f"{obj}.{name}: no elements")
    options: list[str] = []
    if ftype == "enum":
        attr = node.get("options")
        options = _split(attr) if attr is not None else _child_list(node, "options", "option")
        if not options:
            raise ValueError(f"{obj}.{name}: enum without options")
    text = node.get("defaultvalue")
    if text is None:
        if is_settings:
            raise ValueError(f"{obj}.{name}: settings field without defaultvalue")
        defaults: tuple[Any, ...] = (0.0 if ftype == "float" else 0,) * count
    else:
        parts = _split(text)
        if len(parts) == 1:
            parts *= count
        if len(parts) != count:
            raise ValueError(f"{obj}.{name}: {len(parts)} defaults for {count} elements")
        defaults = tuple(_parse_default(obj, name, ftype, options, p) for p in parts)
    return FieldDef(name, ftype, count, tuple(options), defaults, tuple(names))


def _spec(node: ET.Element | None, what: str, obj: str, acked: bool = True) -> TelemetrySpec:
    if node is None:
        raise ValueError(f"{obj}: <{what}> missing")
    mode = UpdateMode[node.get("updatemode", "").upper()]
    return TelemetrySpec(acked and node.get("acked") == "true", mode, int(node.get("period", "0")))


def _parse_object(node: ET.Element) -> ObjectDef:
    name = node.get("name", "")
    if not name:
        raise ValueError("an object has no name")
    is_settings = node.get("settings") == "true"
    single = node.get("singleinstance") == "true"
    declared: list[FieldDef] = []
    for child in node.findall("field"):
        declared.append(_parse_field(name, child, declared, is_settings))
    access = node.find("access")
    if access is None:
        raise ValueError(f"{name}: <access> missing")
    telemetry = Telemetry(
        flight=_spec(node.find("telemetryflight"), "telemetryflight", name),
        gcs=_spec(node.find("telemetrygcs"), "telemetrygcs", name),
        logging=_spec(node.find("logging"), "logging", name, acked=False),
        flight_access=AccessMode[access.get("flight", "").upper()],
        gcs_access=AccessMode[access.get("gcs", "").upper()],
    )
    desc = node.findtext("description") or ""
    return ObjectDef(name, declared, is_settings=is_settings, single_instance=single,
                     telemetry=telemetry, priority=node.get("priority") == "true",
                     description=desc.strip())


class ObjectSet:
    """The objects of one release, by id and by name (metaobjects resolved by id too)."""

    def __init__(self, objects: list[ObjectDef] | tuple[ObjectDef, ...]) -> None:
        self._by_name: dict[str, ObjectDef] = {}
        self._by_id: dict[int, ObjectDef] = {}
        for obj in objects:
            for item in (obj, MetaDef(obj)):
                if item.id in self._by_id:
                    other = self._by_id[item.id].name
                    raise ValueError(f"{item.name}: id 0x{item.id:08X} also {other}")
                self._by_id[item.id] = item
            self._by_name[obj.name] = obj

    @classmethod
    def load(cls, directory: Path | None = None) -> ObjectSet:
        """Parse every ``*.xml`` of ``directory`` (default: the bundled 16.09 set, cached)."""
        if directory is None:
            return _default_set()
        return _load(Path(directory))

    def by_id(self, object_id: int) -> ObjectDef | None:
        """The object (or metaobject: a :class:`MetaDef`) with this id, None if unknown."""
        return self._by_id.get(object_id)

    def by_name(self, name: str) -> ObjectDef:
        """The data object called ``name``; ``<name>Meta`` gives its metaobject."""
        obj = self._by_name.get(name)
        if obj is None and name.endswith("Meta"):
            parent = self._by_name.get(name[:-4])
            obj = self._by_id[parent.meta_id] if parent is not None else None
        if obj is None:
            raise KeyError(f"no UAVTalk object {name!r}")
        return obj

    def data_length(self, object_id: int) -> int | None:
        """The data length of this id's object (None if unknown)."""
        obj = self._by_id.get(object_id)
        return None if obj is None else obj.size

    def __iter__(self) -> Iterator[ObjectDef]:
        """The data objects (not the metaobjects), sorted by name."""
        return iter(sorted(self._by_name.values(), key=lambda o: o.name))

    def __len__(self) -> int:
        return len(self._by_name)

    def __contains__(self, name: object) -> bool:
        return name in self._by_name


def _load(directory: Path | Traversable) -> ObjectSet:
    objects: list[ObjectDef] = []
    entries = sorted((e for e in directory.iterdir() if e.name.endswith(".xml")),
                     key=lambda e: e.name)
    for entry in entries:
        with entry.open("rb") as stream:
            root = ET.parse(stream).getroot()
        for node in root.findall("object"):
            try:
                objects.append(_parse_object(node))
            except (ValueError, KeyError) as exc:
                raise ValueError(f"{entry.name}: {exc}") from exc
    return ObjectSet(objects)


@functools.cache
def _default_set() -> ObjectSet:
    # a Traversable, not a path: works from a wheel or a zip as well
    return _load(resources.files("dialects") / "uavtalk")
