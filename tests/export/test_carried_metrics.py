"""quietframe-export --metrics-from: a re-export carries the measured tables and names the
version that measured them, even across several re-exports."""

from __future__ import annotations

import json

import pytest

onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper  # noqa: E402

from quietframe.export.cli import carried_metrics  # noqa: E402


def tiny_model(path, version: str, training: dict, metrics: dict) -> None:
    node = helper.make_node("Identity", ["x"], ["y"])
    graph = helper.make_graph([node], "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT,
                                                                          [1])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1])])
    model = helper.make_model(graph)
    for key, value in (("quietframe.version", version),
                       ("quietframe.training", json.dumps(training)),
                       ("quietframe.metrics", json.dumps(metrics))):
        model.metadata_props.append(onnx.StringStringEntryProto(key=key, value=value))
    onnx.save(model, str(path))


def test_the_measuring_version_survives_a_second_carry(tmp_path):
    tables = {"cycles": {"psnr": [30.0]}}
    first = tmp_path / "v2.onnx"
    tiny_model(first, "2", {"trained": False}, tables)
    notes, metrics = carried_metrics(first, {"trained": False})
    assert metrics == tables and notes["tables_measured_with_version"] == "2"
    second = tmp_path / "v3.onnx"
    tiny_model(second, "3", notes, metrics)  # version 3 carried version 2's tables
    notes, metrics = carried_metrics(second, {"trained": False})
    assert metrics == tables and notes["tables_measured_with_version"] == "2"


@pytest.mark.parametrize("variant", ["aligned-accumulation", "oidn-history"])
def test_an_untrained_stage_re_exported_keeps_its_tables(tmp_path, variant):
    """The accumulation and the output-history tiers (no learned parameters) are re-exported
    when their rule changes; their measured tables travel with them."""
    pytest.importorskip("torch")
    from quietframe.export.cli import main

    tables = {"cycles": {"by_spp": [{"spp": 1, "psnr": 30.0}]}}
    old = tmp_path / "old.onnx"
    tiny_model(old, "1", {"trained": False}, tables)
    new = tmp_path / f"{variant}.onnx"
    assert main(["--variant", variant, "--version", "2", "--metrics-from", str(old),
                 "--out", str(new)]) == 0
    props = {p.key: p.value for p in onnx.load(str(new)).metadata_props}
    assert json.loads(props["quietframe.metrics"]) == tables
    assert json.loads(props["quietframe.training"])["tables_measured_with_version"] == "1"


def test_a_fine_tuned_checkpoint_carries_the_old_tables_beside_its_selection(tmp_path):
    """A fine-tune whose tables cannot be measured again here (their split is not rendered)
    ships with the old version's tables, its own selection record on top."""
    torch = pytest.importorskip("torch")
    from quietframe.export.cli import main
    from quietframe.model.families import family_of_variant

    model = family_of_variant("nbg-2l-3g").variant("nbg-2l-3g", width=4)
    selection = {"selected_on": "corpus", "zoo_psnr": 27.5, "step": 250}
    checkpoint = tmp_path / "best.pt"
    torch.save({"config": model.config.to_dict(), "model": model.state_dict(),
                "training": {"variant": "nbg-2l-3g", "steps_done": 250},
                "metrics": selection}, checkpoint)
    old = tmp_path / "old.onnx"
    tables = {"by_renderer": {"cycles": {"by_spp": [{"spp": 1, "psnr": 26.0}]}}, "step": 400}
    tiny_model(old, "5", {"steps_done": 400}, tables)
    new = tmp_path / "nbg-2l-3g.onnx"
    assert main(["--checkpoint", str(checkpoint), "--version", "6", "--metrics-from", str(old),
                 "--out", str(new)]) == 0
    props = {p.key: p.value for p in onnx.load(str(new)).metadata_props}
    assert json.loads(props["quietframe.metrics"]) == {**tables, **selection}
    training = json.loads(props["quietframe.training"])
    assert training["tables_measured_with_version"] == "5" and training["steps_done"] == 250
