"""`tf2_msgs/msg/TFMessage` in CDR: `decode_tf_message` and `encode_tf_message`.

Layout: a sequence of `geometry_msgs/TransformStamped`: header (int32 sec, uint32 nanosec, string
frame_id: the parent), string child_frame_id, `Transform` (Vector3 translation: 3 float64;
Quaternion rotation: x, y, z, w float64).
"""

from __future__ import annotations

from dataclasses import dataclass

from fleetmap.ros.cdr import CdrError, CdrReader, CdrWriter

ROS_TYPE = "tf2_msgs/msg/TFMessage"
#: The fewest bytes one TransformStamped takes (two empty strings, seven float64): a count above
#: remaining / this is refused before looping.
_MIN_TRANSFORM_BYTES = 4 + 4 + 4 + 4 + 56


@dataclass(frozen=True)
class TransformStamped:
    """One TF edge sample: the pose of `child` in `parent` at `stamp` (seconds). Frame ids as sent
    (`fleetmap.ros.transforms` normalises them)."""

    stamp: float
    parent: str
    child: str
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]  # x, y, z, w


def decode_tf_message(payload: bytes, max_transforms: int = 1000) -> list[TransformStamped]:
    """Decode a whole TFMessage; raises `CdrError` if it is not one or holds more than
    `max_transforms` transforms."""
    r = CdrReader(payload)
    n = r.sequence_length(_MIN_TRANSFORM_BYTES)
    if n > max_transforms:
        raise CdrError(f"a TFMessage of {n} transforms is more than the limit of {max_transforms}")
    out = []
    for _ in range(n):
        sec, nanosec = r.int32(), r.uint32()
        parent = r.string()
        child = r.string()
        t = (r.float64(), r.float64(), r.float64())
        q = (r.float64(), r.float64(), r.float64(), r.float64())
        out.append(TransformStamped(sec + nanosec * 1e-9, parent, child, t, q))
    if r.remaining > 7:
        raise CdrError(f"{r.remaining} bytes after the end of a TFMessage")
    return out


def encode_tf_message(transforms: list[TransformStamped]) -> bytes:
    """A TFMessage payload (little-endian CDR). Stamps are split into sec and nanosec."""
    w = CdrWriter()
    w.write_sequence_length(len(transforms))
    for t in transforms:
        sec = int(t.stamp // 1)
        nanosec = min(round((t.stamp - sec) * 1e9), 999_999_999)
        w.write_int32(sec)
        w.write_uint32(nanosec)
        w.write_string(t.parent)
        w.write_string(t.child)
        for v in (*t.translation, *t.rotation):
            w.write_float64(v)
    return w.getvalue()


__all__ = ["ROS_TYPE", "TransformStamped", "decode_tf_message", "encode_tf_message"]
