"""Staged runs: the committed state (weights exact, Adam moments in 8 bits) and `--continue` from it."""

import json

import torch

from gomatch_train import run_state, stage, train
from gomatch_train.export import load_export
from test_training import cli


def test_moment_codes_keep_their_precision():
    torch.manual_seed(0)
    first = torch.randn(3000) * torch.logspace(-6, 0, 3000)
    back = run_state.dequantize_signed(run_state.quantize_signed(first))
    for block, restored in zip(run_state.blocks(first), run_state.blocks(back)):
        assert (restored - block).abs().max() <= block.abs().max() / 254 + 1e-12
    second = torch.rand(70_001) * torch.logspace(-9, -2, 70_001)
    second[::7] = 0
    back = run_state.dequantize_log(run_state.quantize_log(second))
    positive = second > 0
    assert torch.equal(back[~positive], second[~positive]), "zeros must stay exactly zero"
    assert ((back[positive] - second[positive]).abs() / second[positive]).max() < 0.03
    assert back.shape == second.shape


def test_continue_restores_the_packed_weights_and_adam_state(data, tmp_path):
    first = tmp_path / "first"
    train.main(cli(data, first, "--epochs", "1"))
    checkpoint = torch.load(first / "checkpoint.pt", weights_only=False)
    assert checkpoint["samples"] > 0 and checkpoint["train_totals"]["samples"] > 0
    packed = run_state.pack(checkpoint, {"stages": 1, "samples": checkpoint["samples"], "cpu_minutes": 0.1})
    path = tmp_path / "state.pt"
    run_state.save(packed, str(path))
    assert path.stat().st_size < 8 * sum(t.numel() for t in checkpoint["model"].values()) + 200_000

    run = train.Run(train.parse_args(cli(data, tmp_path / "second", "--continue", str(path), "--lr", "5e-4")))
    assert all(torch.equal(t, checkpoint["model"][name]) for name, t in run.model.state_dict().items())
    restored = run.optimizer.state_dict()
    assert restored["param_groups"][0]["lr"] == 5e-4
    for index, state in checkpoint["optimizer"]["state"].items():
        got = restored["state"][index]
        assert float(got["step"]) == float(state["step"])
        torch.testing.assert_close(got["exp_avg"], state["exp_avg"], atol=state["exp_avg"].abs().max() / 200, rtol=0)
        torch.testing.assert_close(got["exp_avg_sq"], state["exp_avg_sq"], rtol=0.07, atol=1e-30)
    train.main(cli(data, tmp_path / "second", "--continue", str(path), "--epochs", "1"))
    assert (tmp_path / "second" / "last.safetensors").exists()


def test_schedule_gives_the_point_budget_and_outlier_rate_of_the_run_part():
    schedule = json.loads(
        '[{"until_samples": 1000, "max_points": 256}, {"max_points": 1024, "outlier_rate": [0.5, 0.9]}]'
    )
    assert stage.part_for(schedule, 0)["max_points"] == 256
    assert stage.part_for(schedule, 999)["max_points"] == 256
    assert stage.part_for(schedule, 1000)["max_points"] == 1024
    assert stage.part_for([{"max_points": 256}], 10**9)["max_points"] == 256
    assert stage.budget_cell(stage.part_for(schedule, 0)) == "256"
    assert stage.budget_cell(stage.part_for(schedule, 1000)) == "1024, outliers 0.5-0.9"
    assert stage.budget_cell({"max_points": 256, "data_capacity": 256}) == "256, caps 256"


def test_validation_samples_have_the_caps_of_the_training_data(tmp_path):
    capped, uncapped = {"max_points": 256, "data_capacity": 256}, {"max_points": 256}
    assert stage.capacity_arguments(capped) == ["--capacity", "256"]
    assert stage.capacity_arguments(uncapped) == []
    assert stage.validation_file(tmp_path, capped) != stage.validation_file(tmp_path, uncapped)
    assert stage.validation_file(tmp_path, uncapped) == tmp_path / "val.safetensors"


def test_a_run_folder_names_the_weights_of_its_committed_state(data, tmp_path):
    train.main(cli(data, tmp_path / "run", "--epochs", "1"))
    checkpoint = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)
    folder = tmp_path / "stages" / "other"
    folder.mkdir(parents=True)
    run_state.save(run_state.pack(checkpoint, {"samples": 6, "cpu_minutes": 0.0, "stages": 1}), str(folder / "state.pt"))
    exported = stage.export_of(str(folder), tmp_path / "weights.safetensors")
    model = load_export(str(exported))
    assert all(torch.equal(t, checkpoint["model"][name]) for name, t in model.state_dict().items())
    file = tmp_path / "run" / "last.safetensors"
    assert stage.export_of(str(file), tmp_path / "unused.safetensors") == file
