import json
import subprocess
import sys

import pytest

from jaxtraj.cli import EXIT_OK, EXIT_USAGE, main


def test_demo_small_writes_results_and_meets_accuracy(tmp_path, capsys):
    out = tmp_path / "demo"
    rc = main(["demo", "--paper", "--frames", "60", "--k", "12", "--out", str(out), "--seed", "1"])
    assert rc == EXIT_OK
    text = capsys.readouterr().out
    assert "mean error" in text and "6-DoF pose" in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["point"]["ok"] and summary["method"] == "dct"
    # 60 frames over 10 s at 0.3 px: a few millimetres at most (150 frames: ~0.5 mm).
    assert summary["point"]["mean_error_mm"] < 5.0
    assert summary["pose_6dof"]["mean_orientation_error_deg"] < 1.0
    for name in ("fig3_trajectory.png", "fig4_errors.png"):
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    assert not list(out.glob("*.part"))


def test_demo_rejects_k_too_large(tmp_path, capsys):
    rc = main(["demo", "--paper", "--frames", "10", "--k", "8", "--out", str(tmp_path)])
    assert rc == EXIT_USAGE
    assert "--k 8 is too large for --frames 10" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv,needle",
    [
        (["demo", "--frames", "0"], "positive integer"),
        (["demo", "--noise", "-1"], "non-negative"),
        (["nonsense"], "invalid choice"),
    ],
)
def test_bad_options_exit_2_with_message(argv, needle, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == EXIT_USAGE
    assert needle in capsys.readouterr().err


def test_console_script_help():
    proc = subprocess.run(
        [sys.executable, "-m", "jaxtraj", "demo", "--help"], capture_output=True, text=True
    )
    assert proc.returncode == 0
    assert "--frames" in proc.stdout and "--noise" in proc.stdout


PAPER_SMALL = ["demo", "--paper", "--frames", "60", "--seed", "2", "--no-plots"]


@pytest.fixture(scope="module")
def paper_dct_summary(tmp_path_factory):
    """summary.json of the paper's method (k = 12) on the small scene the estimators beat."""
    out = tmp_path_factory.mktemp("dct")
    assert main([*PAPER_SMALL, "--k", "12", "--out", str(out)]) == EXIT_OK
    return json.loads((out / "summary.json").read_text())


@pytest.mark.parametrize("method", ["regularised", "smoother"])
def test_demo_better_estimators_beat_the_paper_method(tmp_path, method, paper_dct_summary):
    other = tmp_path / method
    assert main([*PAPER_SMALL, "--method", method, "--out", str(other)]) == EXIT_OK
    a = paper_dct_summary["point"]
    b = json.loads((other / "summary.json").read_text())
    assert b["method"] == method and b["point"]["ok"]
    assert b["point"]["mean_error_mm"] < a["mean_error_mm"]
    assert b["point"]["max_error_mm"] < a["max_error_mm"]


def test_demo_auto_k_beats_the_paper_k_on_the_mean(tmp_path, paper_dct_summary):
    # k chosen by cross-validation (gain-weighted) against the paper's fixed k: lower mean
    # error for the point and for the rigid body's position (max errors at the ends of
    # the recording can be larger with the larger k it picks)
    auto = tmp_path / "auto"
    assert main([*PAPER_SMALL, "--method", "auto-k", "--out", str(auto)]) == EXIT_OK
    a = paper_dct_summary
    b = json.loads((auto / "summary.json").read_text())
    assert b["method"] == "auto-k" and b["point"]["ok"]
    assert "cross-validated" in b["estimator"]
    assert b["point"]["mean_error_mm"] < a["point"]["mean_error_mm"]
    assert b["pose_6dof"]["mean_position_error_mm"] < 0.7 * a["pose_6dof"]["mean_position_error_mm"]
