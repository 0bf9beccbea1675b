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


def test_error_auc_follows_the_rust_trapezoids():
    assert abs(eval_table.error_auc([0.5], 1.0) - 75.0) < 1e-9
    assert abs(eval_table.error_auc([0.5, float("inf")], 1.0) - 37.5) < 1e-9
    assert abs(eval_table.error_auc([4.0, 0.0, 2.0], 5.0) - 100.0 * 11.0 / 15.0) < 1e-9
    assert eval_table.error_auc([1.0], 1.0) == 0.0


def with_queries(seed: int, errors: list) -> dict:
    aucs = tuple(eval_table.error_auc([e if e is not None else float("inf") for e in errors], t) for t in (1, 5, 10))
    content = report("colmap/s", seed, aucs)
    content["per_query"] = [{"image_id": i, "reprojection_px": e} for i, e in enumerate(errors)]
    return content


def test_bootstrap_interval_brackets_the_difference_and_is_reproducible(tmp_path, capsys):
    f32 = [with_queries(0, [0.2, 0.4, 3.0, None, 0.6, 7.0]), with_queries(1, [0.2, 0.5, 3.0, None, 0.6, 7.0])]
    int8 = [with_queries(0, [0.3, 0.4, 3.5, None, 0.9, 6.0]), with_queries(1, [0.3, 0.4, 3.5, 0.8, 0.9, 6.0])]
    full = eval_table.mean_auc_difference(f32, int8, list(range(6)))
    assert all(abs(d - (b - a)) < 1e-9 for d, a, b in zip(full, eval_table.auc_means(f32), eval_table.auc_means(int8)))

    interval = eval_table.bootstrap_interval(f32, int8)
    assert interval == eval_table.bootstrap_interval(f32, int8)
    assert all(lo <= d <= hi and lo < hi for d, (lo, hi) in zip(full, interval))
    assert eval_table.bootstrap_interval(f32, f32) == [(0.0, 0.0)] * 3

    for name, content in [("s-f32.json", f32[0]), ("s-f32-seed1.json", f32[1]),
                          ("s-int8.json", int8[0]), ("s-int8-seed1.json", int8[1])]:  # fmt: skip
        write(tmp_path, name, content)
    eval_table.main(tmp_path)
    spans = " / ".join(f"[{lo:+.2f}, {hi:+.2f}]" for lo, hi in interval)
    assert f"(95 % bootstrap interval over the queries: {spans})" in capsys.readouterr().out


def test_baseline_comparison_uses_the_seeds_both_models_hold(tmp_path, capsys):
    new, old = tmp_path / "new", tmp_path / "old"
    new.mkdir()
    old.mkdir()
    write(new, "s-f32.json", with_queries(0, [0.2, 0.4, 3.0]))
    write(new, "s-f32-seed1.json", with_queries(1, [0.2, 0.4, 2.0]))
    write(old, "s-f32.json", with_queries(0, [0.5, 0.4, None]))
    write(old, "s-f32-seed7.json", with_queries(7, [0.1, 0.1, 0.1]))

    lines = eval_table.baseline_lines({("s", "f32"): eval_table.seed_reports(new, "s", "f32")}, old)
    assert len(lines) == 1
    only_seed_0 = eval_table.mean_auc_difference(
        [with_queries(0, [0.5, 0.4, None])], [with_queries(0, [0.2, 0.4, 3.0])], [0, 1, 2]
    )
    diff = " / ".join(f"{d:+.2f}" for d in only_seed_0)
    assert lines[0].startswith(f"colmap/s: f32 - baseline f32, mean AUC @1/5/10 px: {diff} (95 % bootstrap")

    eval_table.main(new, old)
    assert lines[0] in capsys.readouterr().out


def test_true_match_table_splits_the_queries_at_10_px(tmp_path, capsys):
    def query(error, true_merged, merged, true_inliers, inliers):
        return {"reprojection_px": error, "counts": {"merged": merged, "inliers": inliers},
                "correct": {"merged": true_merged, "inliers": true_inliers}}  # fmt: skip

    content = report("colmap/s", 0, (10.0, 20.0, 30.0))
    content["per_query"] = [query(0.5, 40.0, 300.0, 38.0, 41.0), query(2.0, 20.0, 200.0, 19.0, 22.0),
                            query(None, 1.0, 250.0, 0.0, 5.0), query(80.0, 3.0, 150.0, 0.0, 6.0),
                            query(12.0, 9.0, 100.0, 2.0, 7.0)]  # fmt: skip
    write(tmp_path, "s-f32.json", content)
    older = report("colmap/s", 0, (9.0, 20.0, 30.0))
    older["per_query"] = [{"reprojection_px": 1.0, "counts": {"merged": 1.0, "inliers": 1.0}}]
    write(tmp_path, "s-int8.json", older)

    eval_table.main(tmp_path)
    out = capsys.readouterr().out
    assert "| colmap/s | f32 | 2 | 30 (20-40) of 250 | 28.5 of 31.5 | 3 | 3 (1-9) of 150 | 0 of 6 |" in out
    assert "| colmap/s | int8 |" not in out.split("true inliers of inliers")[1]


def test_validation_table_sets_the_model_beside_the_oracle(tmp_path, capsys):
    model = report("opensfm/p", 0, (10.0, 30.0, 40.0))
    model["per_query"] = [
        {"image_id": i, "reprojection_px": 1.0, "counts": {"merged": m, "inliers": n}, "correct": {"merged": c, "inliers": t}}
        for i, (m, n, c, t) in enumerate([(100, 20, 10, 9), (300, 40, 30, 29), (200, 10, 2, 1)])
    ]  # fmt: skip
    write(tmp_path, "p-int8.json", model)
    write(tmp_path, "p-oracle.json", report("opensfm/p", 0, (80.0, 60.0, 90.0)))
    eval_table.main(tmp_path)
    out = capsys.readouterr().out
    assert ("| opensfm/p | int8 | 4 | 0 (0) | 10.00 / 30.00 / 40.00 | 80.00 / 60.00 / 90.00 | 10 of 200 | 9 of 20 |"
            in out)  # fmt: skip
    assert "| int8 | 1 | 10.00 / 30.00 / 40.00 | 80.00 / 60.00 / 90.00 | 0.500 |" in out
