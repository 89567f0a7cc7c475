"""`senfunet evaluate --seeds-weights`: the spread over training seeds, written as its own section of
results.md (a tiny run through the real command line), and the section splicing."""
from __future__ import annotations

import functools
import hashlib
import re

import pytest

from senfunet_core import networks
from senfunet_core.learning import evaluation as ev
from senfunet_core.learning import report
from senfunet_ros import cli

TINY = {"room_size_m": (2.5, 2.5, 2.4), "image_size": (128, 128)}


def _row(text: str, label: str) -> list[str]:
    line = next(x for x in text.splitlines() if x.startswith(f"| {label} |"))
    return [c.strip() for c in line.strip("|").split("|")][1:]


@pytest.mark.slow  # simulates and scores one small room with two weights files, then once more for the reference
def test_seeds_weights_writes_its_section_and_keeps_the_rest(tmp_path, monkeypatch):
    feature_nets, weighting_net = networks.make_networks((False, True), seed=1, tsdf_input=True)
    other = tmp_path / "seed1.pt"
    networks.save_weights(other, ("tof", "stereo"), feature_nets, weighting_net, meta={"config": {"seed": 1}})
    out = tmp_path / "docs"
    out.mkdir()
    (out / "results.md").write_text("# Results\n\nthe main tables stay\n")
    # the command's rooms, shrunk: one small room at a low resolution
    monkeypatch.setattr(ev, "EvaluationConfig", functools.partial(ev.EvaluationConfig, **TINY))
    argv = ["evaluate", "--set", "validation", "--scenes", "1", "--duration", "0.25", "--frame-stride", "1",
            "--cache-dir", "none", "--out", str(out), "--seeds-weights", str(other)]
    assert cli.main(argv) == 0
    text = (out / "results.md").read_text()
    assert text.startswith("# Results\n\nthe main tables stay\n")
    assert text.count("## Spread over training seeds: validation rooms") == 1
    assert hashlib.sha256(other.read_bytes()).hexdigest() in text
    assert hashlib.sha256(networks.DEFAULT_WEIGHTS.read_bytes()).hexdigest() in text
    shipped = next(x for x in text.splitlines() if x.startswith("| SenFuNet, seed") and "(shipped)" in x)
    seed1 = _row(text, "SenFuNet, seed 1")
    # the shipped weights' row is what the full evaluation gives for the same room
    cfg = ev.EvaluationConfig(seeds=(900,), duration_s=0.25, frame_stride=1, cache_dir=None, async_tof_divisors=())
    reference = ev.evaluate("default", cfg, log=None).rows
    assert float(shipped.strip("|").split("|")[1]) == pytest.approx(reference["senfunet"]["F"], abs=0.005)
    assert float(_row(text, "ToF only")[0]) == pytest.approx(reference["tof"]["F"], abs=0.005)
    assert float(_row(text, "TSDF Fusion (both sensors)")[0]) == pytest.approx(reference["tsdf_fusion"]["F"],
                                                                               abs=0.005)
    # an untrained G with another initialisation fuses differently from the trained one
    assert float(seed1[0]) != pytest.approx(reference["senfunet"]["F"], abs=0.005)
    summary = _row(text, "seed 1")
    assert summary[5] in ("0 of 1", "1 of 1")


def test_seeds_weights_refuses_a_missing_file(tmp_path, capsys):
    argv = ["evaluate", "--out", str(tmp_path), "--seeds-weights", str(tmp_path / "nope.pt")]
    assert cli.main(argv) == 2
    assert "nope.pt" in capsys.readouterr().err  # an error: on stderr
    assert not (tmp_path / "results.md").exists()


def test_splice_replaces_only_its_own_section_and_full_rewrites_keep_it():
    def section(key: str, body: str) -> str:
        return f"{report.SECTION_BEGIN.format(key=key)}\n{body}\n{report.SECTION_END.format(key=key)}\n"

    text = report.splice_section("# Results\n\nmain\n", "seeds-validation", section("seeds-validation", "v1"))
    text = report.splice_section(text, "seeds-held-out", section("seeds-held-out", "h1"))
    text = report.splice_section(text, "seeds-validation", section("seeds-validation", "v2"))
    assert "v1" not in text and text.index("v2") < text.index("h1") and text.startswith("# Results\n\nmain\n")
    assert len(re.findall("<!-- section seeds-validation", text)) == 1
    kept = report.seed_sections(text)
    assert [("v2" in s, "h1" in s) for s in kept] == [(True, False), (False, True)]


def test_grid_truth_is_shared_between_engines_with_the_same_blocks():
    """Another engine over the same frames (other networks) has the same block layout: the truth is
    shared, and looks up what a fresh one would; an engine over other frames gets its own."""
    from senfunet_core.engine import EngineConfig, SenFuNet
    from senfunet_core.readout import voxel_values
    from senfunet_core.learning import simulator

    scene = simulator.make_scene(7, room_size_m=(2.5, 2.5, 2.4))
    seq = simulator.simulate_sequence(scene, 7, duration_s=0.2, width=96, height=96)
    engines = []
    for weights, frames in (("default", seq.frames), ("paper", seq.frames), ("default", seq.frames[:2])):
        engine = SenFuNet(EngineConfig(), weights=networks.resolve_weights(weights))
        ev.integrate_frames(engine, frames)
        engines.append(engine)
    truth = ev.GridTruth(engines[0], scene, 0.1)
    shared = truth.for_engine(engines[1], scene)
    assert shared.values is truth.values and shared.engine is engines[1]
    centres, _ = voxel_values(engines[1], "tof")
    assert (shared.at(centres) == ev.GridTruth(engines[1], scene, 0.1).at(centres)).all()
    own = truth.for_engine(engines[2], scene)
    assert own.values is not truth.values and own.n_blocks == engines[2].grid.n_blocks
