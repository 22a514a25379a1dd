"""bob-sitl run --animate: an animation of the run (GIF without ffmpeg), whole or absent, one frame per logged
instant (thinned to at most max_frames), with what each experiment is about drawn on it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib import animation
from PIL import Image

from sitl.cli import main
from sitl.experiments.animate import animation_format, write_animation
from sitl.experiments.runner import simulate
from sitl.experiments.scenario import load_scenario


def frames_of(path: Path) -> list[np.ndarray]:
    with Image.open(path) as image:
        out = []
        for k in range(image.n_frames):
            image.seek(k)
            out.append(np.asarray(image.convert("RGB")))
        return out


def test_run_animate_writes_a_gif_beside_the_outputs(tmp_path: Path, capsys) -> None:
    out = tmp_path / "hc"
    argv = ["run", "heading-consensus", "--agents", "3", "--duration", "0.5", "--quiet", "--animate", "--out", str(out)]
    assert main(argv) in (0, 1)
    assert f"animation: {out}/animation.gif" in capsys.readouterr().err
    data = (out / "animation.gif").read_bytes()
    assert data[:6] == b"GIF89a"
    frames = frames_of(out / "animation.gif")
    assert len(frames) == 6  # t = 0, 0.1, ..., 0.5 s: log_period_s = 0.1
    assert any(not np.array_equal(frames[0], f) for f in frames[1:])  # the clock and the headings move
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []  # no partial file left


@pytest.mark.parametrize(
    "name, duration_s, agents",
    [
        ("aggregation", 12.0, 5),
        ("perimeter-defense", 3.0, 5),
        ("search-exploration", 2.0, 5),
        ("avoidance-yield", 12.0, None),
    ],
)
def test_each_experiment_kind_animates(tmp_path: Path, name: str, duration_s: float, agents: int | None) -> None:
    """The hull (aggregation), covered bands (perimeter), lights (search), goal and mover (avoidance)."""
    scenario = load_scenario(name).with_overrides(agents, duration_s=duration_s, fidelity="kinematic")
    result = simulate(scenario)
    path = write_animation(result.fleet, result.recorder, tmp_path, max_frames=2, fps=5)
    assert path == tmp_path / "animation.gif"
    frames = frames_of(path)
    assert len(frames) in (2, 3)  # thinned to 2, plus the last frame when the thinning misses it
    assert frames[0].shape[0] > 100 and frames[0].shape[1] > 100


def test_mp4_when_ffmpeg_is_there(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(animation.writers, "is_available", lambda name: name == "ffmpeg")
    assert animation_format() == "mp4"
    monkeypatch.setattr(animation.writers, "is_available", lambda name: False)
    assert animation_format() == "gif"
