"""BVH reader: parsing, forward kinematics, axes, error messages, real CMU takes."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxtraj.io import Y_UP_TO_Z_UP, load_bvh, parse_bvh

TINY = """\
HIERARCHY
ROOT base
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT arm
  {
    OFFSET 0 1 0
    CHANNELS 3 Xrotation Zrotation Yrotation
    End Site
    {
      OFFSET 0 0 2
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.5
1 2 3 0 0 0 0 0 0
1 2 3 90 0 0 90 0 0
1 2 3 0 0 0 90 90 0
"""


def _line_of(text: str, fragment: str) -> int:
    return next(n for n, line in enumerate(text.splitlines(), 1) if fragment in line)


def test_tiny_file_structure():
    m = parse_bvh(TINY)
    assert m.names == ("base", "arm", "arm_end")
    assert m.parents == (-1, 0, 1)
    assert m.end_site == (False, False, True)
    root = ("Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation")
    assert m.channels[0] == root
    assert m.channels[1] == ("Xrotation", "Zrotation", "Yrotation")
    assert m.channels[2] == ()
    assert m.channel_starts == (0, 6, 9)
    np.testing.assert_array_equal(m.offsets, [[0, 0, 0], [0, 1, 0], [0, 0, 2]])
    assert m.num_frames == 3 and m.motion.shape == (3, 9)
    assert m.frame_time == 0.5 and m.duration == 1.0
    np.testing.assert_array_equal(m.times, [0.0, 0.5, 1.0])


def test_tiny_forward_kinematics_by_hand():
    # Frame 0: no rotation. Frame 1: root Rz(90), arm Rx(90): the end offset (0,0,2) goes
    # to Rx (0,-2,0), then Rz (2,0,0). Frame 2: arm Xrotation 90 then Zrotation 90, i.e.
    # R = Rx(90) Rz(90): (0,0,2) -> Rz (0,0,2) -> Rx (0,-2,0).
    expected = np.array(
        [
            [[1, 2, 3], [1, 3, 3], [1, 3, 5]],
            [[1, 2, 3], [0, 2, 3], [2, 2, 3]],
            [[1, 2, 3], [1, 3, 3], [1, 1, 3]],
        ],
        dtype=float,
    )
    np.testing.assert_allclose(parse_bvh(TINY).positions(), expected, atol=1e-12)


def test_channel_order_against_scipy_intrinsic_euler(rng):
    for order in itertools.permutations("XYZ"):
        text = TINY.replace(
            "Xrotation Zrotation Yrotation", " ".join(f"{a}rotation" for a in order)
        )
        m = parse_bvh(text)
        angles = rng.uniform(-170, 170, size=(3, 3))
        m.motion[:, 6:9] = angles
        m.motion[:, 3:6] = 0.0
        R, p = m.global_transforms()
        ref = Rotation.from_euler("".join(order), angles, degrees=True).as_matrix()
        np.testing.assert_allclose(R[:, 1], ref, atol=1e-12)
        np.testing.assert_allclose(p[:, 2], p[:, 1] + ref @ np.array([0, 0, 2.0]), atol=1e-12)
    # The root's own order (Z, Y, X) also applies intrinsically.
    m = parse_bvh(TINY)
    m.motion[:, 3:6] = rng.uniform(-90, 90, size=(3, 3))
    R, _ = m.global_transforms()
    ref = Rotation.from_euler("ZYX", m.motion[:, 3:6], degrees=True).as_matrix()
    np.testing.assert_allclose(R[:, 0], ref, atol=1e-12)


def test_z_up_mapping():
    assert np.linalg.det(Y_UP_TO_Z_UP) == pytest.approx(1.0)
    np.testing.assert_array_equal(Y_UP_TO_Z_UP @ [0, 1, 0], [0, 0, 1])  # BVH up -> +z
    np.testing.assert_array_equal(Y_UP_TO_Z_UP @ [1, 2, 3], [1, -3, 2])
    m = parse_bvh(TINY)
    R, p = m.global_transforms()
    Rz, pz = m.global_transforms(z_up=True)
    np.testing.assert_allclose(pz, p @ Y_UP_TO_Z_UP.T, atol=1e-15)
    np.testing.assert_allclose(Rz, Y_UP_TO_Z_UP @ R, atol=1e-15)


def test_flexible_layout_and_case():
    # Braces on the keyword's line, lower-case channel names, names with spaces, tabs.
    text = (
        "HIERARCHY\nROOT my root {\n\tOFFSET 1 0 0\n\tCHANNELS 3 xposition yposition zposition\n"
        "\tEnd Site {\n\t\tOFFSET 0 0 1\n\t}\n}\nMOTION\nFrames:\t2\nFrame Time:\t0.01\n"
        "0 0 0\n\n1 1 1\n\n"
    )
    m = parse_bvh(text)
    assert m.names == ("my root", "my root_end")
    np.testing.assert_allclose(m.positions()[1], [[2, 1, 1], [2, 1, 2]])


def test_joint_index():
    m = parse_bvh(TINY)
    assert m.joint_index("arm") == 1 and m.joint_index(-1) == 2 and m.joint_index(0) == 0
    with pytest.raises(ValueError, match="joint: 'leg' is not a joint"):
        m.joint_index("leg")
    with pytest.raises(ValueError, match="joint: index 5 out of range"):
        m.joint_index(5)


MALFORMED = [
    # (replace this, with that, the line containing this fragment, message pattern)
    ("OFFSET 0 1 0", "OFFSET 0 1", "CHANNELS 3 X", "expected a number"),
    (
        "Xrotation Zrotation Yrotation",
        "Xrotation Wrotation Yrotation",
        "Wrotation",
        "unknown channel",
    ),
    (
        "Xrotation Zrotation Yrotation",
        "Xrotation Xrotation Yrotation",
        "Xrotation Xrotation",
        "twice",
    ),
    ("JOINT arm", "JIONT arm", "JIONT", "expected JOINT, End Site"),
    ("JOINT arm", "JOINT base", "JOINT base", "duplicate joint name"),
    ("CHANNELS 3 X", "CHANNELS 2.5 X", "CHANNELS 2.5", "non-negative integer"),
    ("1 2 3 90 0 0 90 0 0", "1 2 3 90 0 0 90 0", "1 2 3 90 0 0 90 0", "expected 9 values"),
    ("1 2 3 90 0 0 90 0 0", "1 2 3 90 0 0 90 zero 0", "zero", "non-numeric"),
    ("1 2 3 90 0 0 90 0 0", "1 2 3 90 0 0 90 nan 0", " nan ", "non-finite"),
    ("Frame Time: 0.5", "Frame Time: fast", "Frame Time", "bad frame time"),
    ("Frame Time: 0.5", "Frame Time: -1", "Frame Time", "frame time must be > 0"),
    ("Frames: 3", "Frames: three", "Frames:", "bad frame count"),
    ("Frames: 3", "Frame count: 3", "Frame count", "expected 'Frames:'"),
    ("Frames: 3", "Frames: 2", "1 2 3 0 0 0 90 90 0", "more frame lines"),
    ("HIERARCHY", "HIERARCHIE", "HIERARCHIE", "expected 'HIERARCHY'"),
    ("ROOT base", "JOINT base", "JOINT base", "expected ROOT"),
]


@pytest.mark.parametrize("old, new, fragment, pattern", MALFORMED)
def test_malformed_file_names_file_and_line(tmp_path, old, new, fragment, pattern):
    text = TINY.replace(old, new, 1)
    assert text != TINY
    path = tmp_path / "bad.bvh"
    path.write_text(text)
    line = _line_of(text, fragment)
    with pytest.raises(ValueError, match=pattern) as err:
        load_bvh(path)
    assert str(err.value).startswith(f"{path}, line {line}:")


def test_truncated_files():
    lines = TINY.splitlines()
    with pytest.raises(ValueError, match=r"<string>, line 20: file ends after 2 frame\(s\)"):
        parse_bvh("\n".join(lines[:-1]))
    with pytest.raises(ValueError, match="no MOTION section"):
        parse_bvh("\n".join(lines[:14]))
    # Missing closing brace: the hierarchy runs into MOTION.
    text = TINY.replace("  }\n}\nMOTION", "  }\nMOTION")
    with pytest.raises(ValueError, match=r"line 15: unexpected end of HIERARCHY"):
        parse_bvh(text)
    with pytest.raises(ValueError, match="HIERARCHY has no ROOT"):
        parse_bvh("HIERARCHY\nMOTION\nFrames: 0\nFrame Time: 0.1\n")
    with pytest.raises(ValueError, match="expected 'Frame Time:'"):
        parse_bvh("\n".join(lines[:17]))


def test_load_equals_parse(tmp_path):
    path = tmp_path / "tiny.bvh"
    path.write_text(TINY)
    a, b = load_bvh(path), parse_bvh(TINY)
    assert a.source == str(path) and a.names == b.names
    np.testing.assert_array_equal(a.motion, b.motion)


@pytest.mark.parametrize("name, frames", [("scaled_131_01.bvh", 995), ("scaled_131_03.bvh", 1248)])
def test_cmu_takes(shared_data, name, frames):
    path = shared_data / "cmu_bvh" / name
    m = load_bvh(path)
    header = path.read_text().split("MOTION", 1)[1].splitlines()
    assert header[1] == f"Frames: {frames}" and m.num_frames == frames
    assert m.frame_time == float(header[2].split(":")[1]) == 0.008333
    assert m.motion.shape == (frames, sum(len(c) for c in m.channels)) == (frames, 96)
    assert m.num_joints == 38 and sum(m.end_site) == 7 and m.names[0] == "Hips"
    np.testing.assert_array_equal(m.motion[0, :3], np.array(header[3].split()[:3], float))
    pos = m.positions()
    assert pos.shape == (frames, 38, 3)
    # The root (zero offset) is at its position channels.
    np.testing.assert_allclose(pos[:, 0], m.motion[:, :3], atol=1e-12)
    # FK keeps every bone length at its offset length in every frame.
    for j, parent in enumerate(m.parents):
        if parent >= 0:
            bone = np.linalg.norm(pos[:, j] - pos[:, parent], axis=1)
            np.testing.assert_allclose(bone, np.linalg.norm(m.offsets[j]), atol=1e-9)
    # Y-up: the head is above the hips and the feet near the floor (metres).
    head, toe = m.names.index("Head"), m.names.index("LeftToe")
    assert np.all(pos[:, head, 1] > pos[:, 0, 1] + 0.1)
    assert np.all(m.positions(z_up=True)[:, head, 2] > pos[:, 0, 1] + 0.1)
    assert -0.1 < pos[:, toe, 1].min() < 0.1
