"""eval_table.py: the model card's tables from `gomatch-sim eval` reports, incl. the mean over seeds."""

import json

import eval_table


def report(scene: str, seed: int, aucs: tuple[float, float, float]) -> dict:
    return {
        "scene": scene, "seed": seed, "queries": 4, "failures": 0,
        "auc_1px": aucs[0], "auc_5px": aucs[1], "auc_10px": aucs[2],
        "rot_deg_q": [0.1, 0.2, 0.3], "mean_counts": {"inliers": 12.0}, "mean_timings_ms": {"total": 5.0},
    }  # fmt: skip


def write(folder, name: str, content: dict) -> None:
    (folder / name).write_text(json.dumps(content))


def test_seed_table_averages_every_seed_in_seed_order(tmp_path, capsys):
    write(tmp_path, "s-f32.json", report("colmap/s", 0, (10.0, 20.0, 30.0)))
    write(tmp_path, "s-f32-seed10.json", report("colmap/s", 10, (14.0, 26.0, 36.0)))
    write(tmp_path, "s-f32-seed2.json", report("colmap/s", 2, (12.0, 20.0, 30.0)))
    write(tmp_path, "s-int8.json", report("colmap/s", 0, (9.0, 20.0, 31.0)))
    write(tmp_path, "s-int8-seed2.json", report("colmap/s", 2, (9.0, 22.0, 33.0)))

    assert [r["seed"] for r in eval_table.seed_reports(tmp_path, "s", "f32")] == [0, 2, 10]
    assert eval_table.auc_means(eval_table.seed_reports(tmp_path, "s", "f32")) == [12.0, 22.0, 32.0]

    eval_table.main(tmp_path)
    out = capsys.readouterr().out
    assert "| colmap/s | f32 | 4 | 0 | 10.00 / 20.00 / 30.00 | 0.10 / 0.20 / 0.30 | 12.0 | 5 |" in out
    assert "| colmap/s | f32 | 0, 2, 10 | 12.00 / 22.00 / 32.00 | 10.00-14.00 / 20.00-26.00 / 30.00-36.00 |" in out
    assert "| colmap/s | int8 | 0, 2 | 9.00 / 21.00 / 32.00 |" in out
    assert "colmap/s: int8 - f32, mean AUC @1/5/10 px: -3.00 / -1.00 / +0.00" in out


def test_without_further_seeds_only_the_seed_zero_table_is_printed(tmp_path, capsys):
    write(tmp_path, "s-f32.json", report("colmap/s", 0, (10.0, 20.0, 30.0)))
    eval_table.main(tmp_path)
    out = capsys.readouterr().out
    assert "10.00 / 20.00 / 30.00" in out and "mean AUC" not in out
