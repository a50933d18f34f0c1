"""s3k demo's helpers."""
def test_progress_bar_shows_the_last_validation(tmp_path):
    from s3k.experiments.demo import _short_validation

    run = tmp_path / "run"
    assert _short_validation(run) == ""  # no log yet
    run.mkdir()
    (run / "train.log").write_text(
        "2026-12-01 18:00:00 INFO step 250 validation: rms_px 9.28, rms_px_reproj 8.66, median_mm 12.5, "
        "rms_mm 17.6, layout_ratio 0.9, triangulated 1\n"
        "2026-12-01 18:01:00 INFO step 500 validation: rms_px 6.1, rms_px_reproj 4.2, median_mm 7.7, "
        "rms_mm 9.4, layout_ratio 0.95, triangulated 1\n")
    assert _short_validation(run) == "val median 7.7 mm, rms 9.4 mm"
