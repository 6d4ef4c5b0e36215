"""Reader for BVH (Biovision Hierarchy) motion-capture files.

A BVH file has two sections::

    HIERARCHY
    ROOT Hips
    {
        OFFSET 0 0 0
        CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
        JOINT Chest { OFFSET ... CHANNELS 3 ... End Site { OFFSET ... } }
    }
    MOTION
    Frames: 995
    Frame Time: 0.008333
    <one line of numbers per frame, one number per channel, in hierarchy order>

Forward kinematics (:meth:`BVHMotion.global_transforms`): each joint's local transform
is a translation ``OFFSET + (position channels)`` followed by the rotation
``R = R_a(theta_1) R_b(theta_2) R_c(theta_3)`` for rotation channels listed in the
order ``a, b, c`` (intrinsic rotations, angles in degrees). World pose of a joint:
``R_w_j = R_w_parent R_local``, ``p_w_j = p_w_parent + R_w_parent (offset + position)``.

Axes: BVH files are Y-up (right-handed, the CMU takes in ``shared/data/cmu_bvh`` too).
``z_up=True`` maps a BVH vector ``(x, y, z)`` to ``(x, -z, y)``, the right-handed
rotation by +90 degrees about x (:data:`Y_UP_TO_Z_UP`), so that BVH "up" becomes +z.

This is a host-side (NumPy) reader. Malformed files raise ``ValueError`` with the file
name and the line number.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

__all__ = ["Y_UP_TO_Z_UP", "BVHMotion", "load_bvh", "parse_bvh"]

#: Rotation taking BVH (Y-up) coordinates to a Z-up world: ``(x, y, z) -> (x, -z, y)``.
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

_CHANNEL_NAMES = {
    f"{a}{kind}": f"{a.upper()}{kind}" for a in "xyz" for kind in ("position", "rotation")
}


@dataclasses.dataclass(frozen=True, eq=False)
class BVHMotion:
    """A parsed BVH take: skeleton, channel layout and per-frame channel values.

    Attributes:
        names: (J,) joint names in file order (parents before children). End sites are
            included as joints named ``"<parent>_end"`` with no channels.
        parents: (J,) index of each joint's parent, -1 for a root.
        offsets: (J, 3) joint offsets in the parent's frame [file units; metres here].
        channels: (J,) per joint, the tuple of its channel names in file order, written
            canonically (``"Xposition"``, ``"Zrotation"``, ...).
        frame_time: seconds between frames.
        motion: (T, C) channel values; rotations in degrees.
        end_site: (J,) True for end sites.
        source: file name (or ``"<string>"``) for messages.
    """

    names: tuple[str, ...]
    parents: tuple[int, ...]
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    frame_time: float
    motion: np.ndarray
    end_site: tuple[bool, ...]
    source: str = "<string>"

    @property
    def num_frames(self) -> int:
        return int(self.motion.shape[0])

    @property
    def num_joints(self) -> int:
        return len(self.names)

    @property
    def times(self) -> np.ndarray:
        """(T,) frame times in seconds from the first frame."""
        return np.arange(self.num_frames) * self.frame_time

    @property
    def duration(self) -> float:
        """Seconds from the first to the last frame."""
        return (self.num_frames - 1) * self.frame_time

    @property
    def channel_starts(self) -> tuple[int, ...]:
        """(J,) column of ``motion`` where each joint's channels begin."""
        starts, c = [], 0
        for ch in self.channels:
            starts.append(c)
            c += len(ch)
        return tuple(starts)

    def joint_index(self, joint: str | int) -> int:
        """Index of a joint given by name or index (``ValueError`` if unknown)."""
        if isinstance(joint, (int, np.integer)) and not isinstance(joint, bool):
            if not -self.num_joints <= joint < self.num_joints:
                raise ValueError(f"joint: index {joint} out of range for {self.num_joints} joints")
            return int(joint) % self.num_joints
        if isinstance(joint, str) and joint in self.names:
            return self.names.index(joint)
        raise ValueError(
            f"joint: {joint!r} is not a joint of {self.source}; known: {', '.join(self.names)}"
        )

    def global_transforms(self, *, z_up: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """World orientation and position of every joint by forward kinematics.

        Args:
            z_up: express the result in a Z-up world (see :data:`Y_UP_TO_Z_UP`).

        Returns:
            ``(R_w_j (T, J, 3, 3), p_w_j (T, J, 3))``: joint frame to world rotation and
            joint position [file units].
        """
        T, J = self.num_frames, self.num_joints
        R = np.empty((T, J, 3, 3))
        p = np.empty((T, J, 3))
        for j, (chans, start) in enumerate(zip(self.channels, self.channel_starts, strict=True)):
            R_local = np.broadcast_to(np.eye(3), (T, 3, 3))
            t_local = np.broadcast_to(self.offsets[j], (T, 3)).copy()
            for c, name in enumerate(chans):
                axis = "XYZ".index(name[0])
                values = self.motion[:, start + c]
                if name.endswith("position"):
                    t_local[:, axis] += values
                else:
                    R_local = R_local @ _axis_rotation(axis, np.deg2rad(values))
            parent = self.parents[j]
            if parent < 0:
                R[:, j], p[:, j] = R_local, t_local
            else:
                R[:, j] = R[:, parent] @ R_local
                p[:, j] = p[:, parent] + np.einsum("tij,tj->ti", R[:, parent], t_local)
        if z_up:
            R = np.einsum("ij,tkjl->tkil", Y_UP_TO_Z_UP, R)
            p = p @ Y_UP_TO_Z_UP.T
        return R, p

    def positions(self, *, z_up: bool = False) -> np.ndarray:
        """(T, J, 3) world positions of all joints (and end sites) [file units]."""
        return self.global_transforms(z_up=z_up)[1]


def _axis_rotation(axis: int, angle: np.ndarray) -> np.ndarray:
    """(T, 3, 3) right-handed rotations by ``angle`` [rad] about coordinate ``axis``."""
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros((*np.shape(angle), 3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    out[..., axis, axis] = 1.0
    out[..., i, i] = c
    out[..., j, j] = c
    out[..., i, j] = -s
    out[..., j, i] = s
    return out


class _Tokens:
    """Whitespace tokens of the HIERARCHY section with their line numbers."""

    def __init__(self, lines: list[str], first_line: int, source: str):
        self.items = [(first_line + n, tok) for n, line in enumerate(lines) for tok in line.split()]
        self.end_line = first_line + len(lines)
        self.pos = 0
        self.source = source

    def error(self, line: int, message: str) -> ValueError:
        return ValueError(f"{self.source}, line {line}: {message}")

    def peek(self) -> tuple[int, str] | None:
        return self.items[self.pos] if self.pos < len(self.items) else None

    def next(self, expected: str) -> tuple[int, str]:
        item = self.peek()
        if item is None:
            raise self.error(self.end_line, f"unexpected end of HIERARCHY, expected {expected}")
        self.pos += 1
        return item

    def expect(self, word: str) -> int:
        line, tok = self.next(repr(word))
        if tok.upper() != word.upper():
            raise self.error(line, f"expected {word!r}, got {tok!r}")
        return line

    def number(self, what: str) -> float:
        line, tok = self.next(what)
        try:
            value = float(tok)
        except ValueError:
            raise self.error(line, f"expected a number ({what}), got {tok!r}") from None
        if not np.isfinite(value):
            raise self.error(line, f"{what} must be finite, got {tok!r}")
        return value


class _Skeleton:
    def __init__(self):
        self.names: list[str] = []
        self.parents: list[int] = []
        self.offsets: list[tuple[float, float, float]] = []
        self.channels: list[tuple[str, ...]] = []
        self.end_site: list[bool] = []


def _parse_offset(tok: _Tokens) -> tuple[float, float, float]:
    tok.expect("OFFSET")
    return tuple(tok.number(f"OFFSET {a}") for a in "xyz")  # type: ignore[return-value]


def _parse_joint(tok: _Tokens, sk: _Skeleton, parent: int, keyword_line: int) -> None:
    name_parts = []
    while (item := tok.peek()) is not None and item[0] == keyword_line and item[1] != "{":
        name_parts.append(tok.next("a joint name")[1])
    if not name_parts:
        raise tok.error(keyword_line, "missing joint name after ROOT/JOINT")
    name = " ".join(name_parts)
    if name in sk.names:
        raise tok.error(keyword_line, f"duplicate joint name {name!r}")
    tok.expect("{")
    index = len(sk.names)
    sk.names.append(name)
    sk.parents.append(parent)
    sk.offsets.append(_parse_offset(tok))
    sk.end_site.append(False)
    line = tok.expect("CHANNELS")
    count = tok.number("number of channels")
    if count != int(count) or count < 0:
        raise tok.error(line, f"CHANNELS count must be a non-negative integer, got {count}")
    chans = []
    for _ in range(int(count)):
        cline, ctok = tok.next("a channel name")
        canonical = _CHANNEL_NAMES.get(ctok.lower())
        if canonical is None:
            raise tok.error(
                cline, f"unknown channel {ctok!r}; expected X/Y/Z followed by position/rotation"
            )
        if canonical in chans:
            raise tok.error(cline, f"channel {canonical} listed twice for joint {name!r}")
        chans.append(canonical)
    sk.channels.append(tuple(chans))
    n_ends = 0
    while True:
        line, word = tok.next("JOINT, End Site or '}'")
        key = word.upper()
        if key == "}":
            return
        if key == "JOINT":
            _parse_joint(tok, sk, index, line)
        elif key == "END":
            tok.expect("Site")
            tok.expect("{")
            offset = _parse_offset(tok)
            tok.expect("}")
            n_ends += 1
            sk.names.append(f"{name}_end" + ("" if n_ends == 1 else str(n_ends)))
            sk.parents.append(index)
            sk.offsets.append(offset)
            sk.channels.append(())
            sk.end_site.append(True)
        else:
            raise tok.error(line, f"expected JOINT, End Site or '}}', got {word!r}")


def _header_value(lines, start, source, label) -> tuple[int, str]:
    """Find the next non-blank line, check it starts with ``label``, return its value."""
    n = start
    while n < len(lines) and not lines[n].strip():
        n += 1
    if n == len(lines):
        raise ValueError(f"{source}, line {n}: unexpected end of file, expected {label!r}")
    text = lines[n].strip()
    if not text.lower().startswith(label.lower()):
        raise ValueError(f"{source}, line {n + 1}: expected {label!r}, got {text[:40]!r}")
    return n, text[len(label) :].strip()


def parse_bvh(text: str, *, source: str = "<string>") -> BVHMotion:
    """Parse the text of a BVH file (see the module docstring for the format).

    Args:
        text: the whole file.
        source: name used in error messages.

    Raises:
        ValueError: ``"<source>, line N: ..."`` on any syntax or consistency error.
    """
    lines = text.splitlines()
    motion_line = next(
        (n for n, line in enumerate(lines) if line.split()[:1] and line.split()[0] == "MOTION"),
        None,
    )
    if motion_line is None:
        raise ValueError(f"{source}, line {len(lines)}: no MOTION section found")

    tok = _Tokens(lines[:motion_line], 1, source)
    tok.expect("HIERARCHY")
    sk = _Skeleton()
    while tok.peek() is not None:
        line, word = tok.next("ROOT")
        if word.upper() != "ROOT":
            raise tok.error(line, f"expected ROOT, got {word!r}")
        _parse_joint(tok, sk, -1, line)
    if not sk.names:
        raise tok.error(motion_line + 1, "HIERARCHY has no ROOT joint")

    n, value = _header_value(lines, motion_line + 1, source, "Frames:")
    try:
        n_frames = int(value)
    except ValueError:
        raise ValueError(f"{source}, line {n + 1}: bad frame count {value!r}") from None
    if n_frames < 0:
        raise ValueError(f"{source}, line {n + 1}: negative frame count {n_frames}")
    frames_line = n + 1
    n, value = _header_value(lines, n + 1, source, "Frame Time:")
    try:
        frame_time = float(value)
    except ValueError:
        raise ValueError(f"{source}, line {n + 1}: bad frame time {value!r}") from None
    if not (np.isfinite(frame_time) and frame_time > 0):
        raise ValueError(f"{source}, line {n + 1}: frame time must be > 0, got {frame_time}")

    n_channels = sum(len(c) for c in sk.channels)
    rows = []
    for m in range(n + 1, len(lines)):
        parts = lines[m].split()
        if not parts:
            continue
        if len(rows) == n_frames:
            raise ValueError(
                f"{source}, line {m + 1}: more frame lines than 'Frames: {n_frames}' "
                f"(line {frames_line})"
            )
        if len(parts) != n_channels:
            raise ValueError(
                f"{source}, line {m + 1}: expected {n_channels} values per frame (the total "
                f"of the CHANNELS counts), got {len(parts)}"
            )
        try:
            row = np.array(parts, dtype=float)
        except ValueError:
            raise ValueError(f"{source}, line {m + 1}: non-numeric value in frame data") from None
        if not np.all(np.isfinite(row)):
            raise ValueError(f"{source}, line {m + 1}: non-finite value in frame data")
        rows.append(row)
    if len(rows) != n_frames and n_channels > 0:
        raise ValueError(
            f"{source}, line {len(lines)}: file ends after {len(rows)} frame(s) but "
            f"'Frames: {n_frames}' (line {frames_line}) announced {n_frames}"
        )
    if n_channels == 0:
        motion = np.zeros((n_frames, 0))
    else:
        motion = np.array(rows, dtype=float).reshape(n_frames, n_channels)
    return BVHMotion(
        names=tuple(sk.names),
        parents=tuple(sk.parents),
        offsets=np.array(sk.offsets, dtype=float),
        channels=tuple(sk.channels),
        frame_time=frame_time,
        motion=motion,
        end_site=tuple(sk.end_site),
        source=source,
    )


def load_bvh(path: str | os.PathLike) -> BVHMotion:
    """Read and parse a BVH file; errors name the file and line."""
    path = Path(path)
    try:
        text = path.read_text()
    except UnicodeDecodeError as err:
        raise ValueError(f"{path}: not a text file ({err})") from None
    return parse_bvh(text, source=str(path))
