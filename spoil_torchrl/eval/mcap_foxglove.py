"""Foxglove's well-known message types as JSON: their JSON schemas, message builders, a validator, images.

The schemas follow Foxglove's published JSON schemas for ``foxglove.FrameTransform``, ``foxglove.SceneUpdate``
(with every primitive list of ``foxglove.SceneEntity``) and ``foxglove.CompressedImage``: same titles, field
names, types and required fields; the recent optional provenance fields (``message_id``, ``lineage``) are left
out. They are written by hand rather than taken from the ``foxglove-sdk`` package, which ships these types as
protobuf only and writes MCAP through its own writer. Foxglove picks the 3D / Image panel renderers by the
schema *name*, so JSON messages with these schemas show up like the SDK's.

Examples:
    >>> message = frame_transform(1_500_000_000, [1.0, 2.0, 0.1], [0.0, 0.0, 0.0, 1.0])
    >>> message["timestamp"], message["parent_frame_id"], message["child_frame_id"]
    ({'sec': 1, 'nsec': 500000000}, 'world', 'agent')
    >>> validate_json(message, FRAME_TRANSFORM_SCHEMA)
    >>> validate_json(dict(message, timestamp={"sec": -1, "nsec": 0}), FRAME_TRANSFORM_SCHEMA)
    Traceback (most recent call last):
    ...
    ValueError: foxglove.FrameTransform: $.timestamp.sec = -1 is below the minimum 0
"""

from __future__ import annotations

import base64
import io
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

WORLD_FRAME = "world"
AGENT_FRAME = "agent"
CAMERA_FRAME = "camera"
IMAGE_FORMATS = ("jpeg", "png")


def _obj(title: str | None, properties: dict[str, Any], description: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {"title": title} if title else {}
    if description:
        out["description"] = description
    out.update(type="object", properties=properties, required=list(properties))
    return out


def _num(description: str = "") -> dict[str, Any]:
    return {"type": "number", "description": description} if description else {"type": "number"}


def _array(items: dict[str, Any], description: str) -> dict[str, Any]:
    return {"type": "array", "items": items, "description": description}


_STRING = {"type": "string"}
_BOOL = {"type": "boolean"}
_BASE64 = {"type": "string", "contentEncoding": "base64"}


def _time(title: str = "time", signed: bool = False) -> dict[str, Any]:
    sec = {"type": "integer"} if signed else {"type": "integer", "minimum": 0}
    nsec = {"type": "integer", "minimum": 0, "maximum": 999_999_999}
    return {"type": "object", "title": title, "properties": {"sec": sec, "nsec": nsec}}


def _xyz(title: str) -> dict[str, Any]:
    return _obj(title, {k: _num(f"{k} coordinate") for k in "xyz"})


VECTOR3 = _xyz("foxglove.Vector3")
POINT3 = _xyz("foxglove.Point3")
QUATERNION = _obj("foxglove.Quaternion", {k: _num(f"{k} value") for k in "xyzw"})
POSE = _obj("foxglove.Pose", {"position": VECTOR3, "orientation": QUATERNION})
COLOR = _obj("foxglove.Color", {k: _num(f"{k} value between 0 and 1") for k in "rgba"})
_COLORS = _array(COLOR, "per-point colors")
_INDICES = _array({"type": "integer", "minimum": 0}, "indices into points")


def _one_of(title: str, values: Sequence[str]) -> dict[str, Any]:
    return {"title": title, "oneOf": [{"title": name, "const": i} for i, name in enumerate(values)]}


_PRIMITIVES: dict[str, dict[str, Any]] = {
    "arrows": _obj(
        "foxglove.ArrowPrimitive",
        {
            "pose": POSE,
            **{k: _num() for k in ("shaft_length", "shaft_diameter", "head_length", "head_diameter")},
        }
        | {"color": COLOR},
    ),
    "cubes": _obj("foxglove.CubePrimitive", {"pose": POSE, "size": VECTOR3, "color": COLOR}),
    "spheres": _obj("foxglove.SpherePrimitive", {"pose": POSE, "size": VECTOR3, "color": COLOR}),
    "cylinders": _obj(
        "foxglove.CylinderPrimitive",
        {"pose": POSE, "size": VECTOR3, "bottom_scale": _num(), "top_scale": _num(), "color": COLOR},
    ),
    "lines": _obj(
        "foxglove.LinePrimitive",
        {
            "type": _one_of("foxglove.LineType", ("LINE_STRIP", "LINE_LOOP", "LINE_LIST")),
            "pose": POSE,
            "thickness": _num(),
            "scale_invariant": _BOOL,
            "points": _array(POINT3, "points along the line"),
            "color": COLOR,
            "colors": _COLORS,
            "indices": _INDICES,
        },
    ),
    "triangles": _obj(
        "foxglove.TriangleListPrimitive",
        {
            "pose": POSE,
            "points": _array(POINT3, "vertices"),
            "color": COLOR,
            "colors": _COLORS,
            "indices": _INDICES,
        },
    ),
    "texts": _obj(
        "foxglove.TextPrimitive",
        {
            "pose": POSE,
            "billboard": _BOOL,
            "font_size": _num(),
            "scale_invariant": _BOOL,
            "color": COLOR,
            "text": _STRING,
        },
    ),
    "models": _obj(
        "foxglove.ModelPrimitive",
        {
            "pose": POSE,
            "scale": VECTOR3,
            "color": COLOR,
            "override_color": _BOOL,
            "url": _STRING,
            "media_type": _STRING,
            "data": _BASE64,
        },
    ),
}

_KEY_VALUE = _obj("foxglove.KeyValuePair", {"key": _STRING, "value": _STRING})
SCENE_ENTITY = _obj(
    "foxglove.SceneEntity",
    {
        "timestamp": _time(),
        "frame_id": _STRING,
        "id": _STRING,
        "lifetime": _time("duration", signed=True),
        "frame_locked": _BOOL,
        "metadata": _array(_KEY_VALUE, "additional metadata"),
        **{name: _array(spec, f"{name} primitives") for name, spec in _PRIMITIVES.items()},
    },
    "A visual element in a 3D scene",
)
_DELETION = _obj(
    "foxglove.SceneEntityDeletion",
    {
        "timestamp": _time(),
        "type": _one_of("foxglove.SceneEntityDeletionType", ("MATCHING_ID", "ALL")),
        "id": _STRING,
    },
)

#: ``foxglove.FrameTransform``: the pose of a child frame in its parent frame.
FRAME_TRANSFORM_SCHEMA = _obj(
    "foxglove.FrameTransform",
    {
        "timestamp": _time(),
        "parent_frame_id": _STRING,
        "child_frame_id": _STRING,
        "translation": VECTOR3,
        "rotation": QUATERNION,
    },
    "A transform between two reference frames in 3D space",
)
#: ``foxglove.SceneUpdate``: entities to add or replace (and deletions) in the 3D panel.
SCENE_UPDATE_SCHEMA = _obj(
    "foxglove.SceneUpdate",
    {"deletions": _array(_DELETION, "entities to delete"), "entities": _array(SCENE_ENTITY, "entities")},
    "An update to the entities displayed in a 3D scene",
)
#: ``foxglove.CompressedImage``: a JPEG / PNG frame.
COMPRESSED_IMAGE_SCHEMA = _obj(
    "foxglove.CompressedImage",
    {"timestamp": _time(), "frame_id": _STRING, "data": _BASE64, "format": _STRING},
    "A compressed image",
)


def time_of(ns: int) -> dict[str, int]:
    """A Foxglove ``time`` from nanoseconds."""
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def frame_transform(time_ns: int, position: Sequence[float], quaternion_xyzw: Sequence[float]) -> dict:
    """A ``foxglove.FrameTransform`` from :data:`WORLD_FRAME` to :data:`AGENT_FRAME`."""
    return {
        "timestamp": time_of(time_ns),
        "parent_frame_id": WORLD_FRAME,
        "child_frame_id": AGENT_FRAME,
        "translation": dict(zip("xyz", map(float, position), strict=True)),
        "rotation": dict(zip("xyzw", map(float, quaternion_xyzw), strict=True)),
    }


def identity_pose(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> dict:
    """A ``foxglove.Pose`` at ``(x, y, z)`` with no rotation."""
    position = {"x": float(x), "y": float(y), "z": float(z)}
    return {"position": position, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}


def color(r: float, g: float, b: float, a: float = 1.0) -> dict:
    """A ``foxglove.Color``."""
    return {"r": float(r), "g": float(g), "b": float(b), "a": float(a)}


def scene_entity(entity_id: str, time_ns: int, **primitives: list[dict]) -> dict:
    """A ``foxglove.SceneEntity`` in the world frame that lasts until replaced (every primitive list present)."""
    unknown = set(primitives) - set(_PRIMITIVES)
    if unknown:
        raise ValueError(f"unknown primitive list(s) {sorted(unknown)}; known: {sorted(_PRIMITIVES)}")
    return {
        "timestamp": time_of(time_ns),
        "frame_id": WORLD_FRAME,
        "id": entity_id,
        "lifetime": {"sec": 0, "nsec": 0},
        "frame_locked": False,
        "metadata": [],
        **{name: list(primitives.get(name, [])) for name in _PRIMITIVES},
    }


def scene_update(time_ns: int, entities: Sequence[Mapping[str, Any]]) -> dict:
    """A ``foxglove.SceneUpdate`` with the given entities (``(id, primitives)`` mappings, see
    :func:`scene_entity`), all stamped ``time_ns``."""
    return {
        "deletions": [],
        "entities": [scene_entity(e["id"], time_ns, **e["primitives"]) for e in entities],
    }


def encode_image(image: np.ndarray, image_format: str = "jpeg", *, quality: int = 85) -> bytes:
    """An ``H x W x 3`` (or ``H x W``) uint8 image as JPEG or PNG bytes (Pillow).

    Examples:
        >>> frame = np.zeros((4, 6, 3), dtype=np.uint8); frame[:, :3, 0] = 255
        >>> decode_image(encode_image(frame, "png")).shape, bool((decode_image(encode_image(frame, "png")) == frame).all())
        ((4, 6, 3), True)
    """
    from PIL import Image

    if image_format not in IMAGE_FORMATS:
        raise ValueError(f"image format must be one of {IMAGE_FORMATS}, got {image_format!r}")
    array = np.asarray(image)
    if array.dtype != np.uint8 or array.ndim not in (2, 3) or (array.ndim == 3 and array.shape[2] != 3):
        raise ValueError(f"expected an H x W x 3 or H x W uint8 image, got {array.dtype} {array.shape}")
    out = io.BytesIO()
    options = {"quality": int(quality)} if image_format == "jpeg" else {}
    Image.fromarray(array).save(out, format=image_format.upper(), **options)
    return out.getvalue()


def decode_image(data: bytes) -> np.ndarray:
    """The pixels of JPEG / PNG bytes as a uint8 array."""
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)))


def compressed_image(time_ns: int, data: bytes, image_format: str) -> dict:
    """A ``foxglove.CompressedImage`` of already encoded bytes (base64 in JSON)."""
    return {
        "timestamp": time_of(time_ns),
        "frame_id": CAMERA_FRAME,
        "data": base64.b64encode(data).decode("ascii"),
        "format": image_format,
    }


_JSON_TYPES = {
    "object": (dict,),
    "array": (list,),
    "string": (str,),
    "boolean": (bool,),
    "number": (int, float),
    "integer": (int,),
}


def _problems(value: Any, schema: Mapping[str, Any], where: str):
    if "oneOf" in schema:
        if not any(value == option["const"] and not isinstance(value, bool) for option in schema["oneOf"]):
            yield f"{where} = {value!r} is not one of {[o['const'] for o in schema['oneOf']]}"
        return
    kind = schema.get("type")
    if kind is not None:
        if not isinstance(value, _JSON_TYPES[kind]) or (isinstance(value, bool) and kind != "boolean"):
            yield f"{where} = {str(value)[:40]} is not of type {kind}"
            return
    if "minimum" in schema and value < schema["minimum"]:
        yield f"{where} = {value} is below the minimum {schema['minimum']}"
    if "maximum" in schema and value > schema["maximum"]:
        yield f"{where} = {value} is above the maximum {schema['maximum']}"
    if schema.get("contentEncoding") == "base64":
        try:
            base64.b64decode(value, validate=True)
        except ValueError:
            yield f"{where} is not base64"
    if kind == "object":
        for name in schema.get("required", ()):
            if name not in value:
                yield f"{where}.{name} is missing"
        for name, spec in schema.get("properties", {}).items():
            if name in value:
                yield from _problems(value[name], spec, f"{where}.{name}")
    elif kind == "array":
        for i, item in enumerate(value):
            yield from _problems(item, schema["items"], f"{where}[{i}]")


def validate_json(message: Any, schema: Mapping[str, Any]) -> None:
    """Check a decoded JSON message against a JSON schema (the subset these schemas use: types, required
    fields, bounds, ``oneOf`` constants, base64 strings); raises ``ValueError`` with the first problem."""
    for problem in _problems(message, schema, "$"):
        raise ValueError(f"{schema.get('title', 'message')}: {problem}")
