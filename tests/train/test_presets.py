"""Named configurations (``s3k train --preset``): the preset's fields and two-pass options, with what the
command line gives winning."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from helpers.synthetic_rig import make_dataset

from s3k import cli
from s3k.config import TrainConfig
from s3k.train.presets import PRESETS


def test_every_preset_is_a_whole_valid_configuration_printed_by_the_cli(capsys):
    for name, chosen in PRESETS.items():
        assert isinstance(chosen.config, TrainConfig)
        chosen.config.validate()
        assert TrainConfig.from_flat(**chosen.config.to_dict()) == chosen.config  # it saves and reads whole
        capsys.readouterr()
        argv = ["train", "data", "--out", "run", "--preset", name, "--print-config", "--seed", "3"]
        assert cli.main(argv) == 0
        printed = json.loads(capsys.readouterr().out)
        assert printed == {**chosen.config.to_dict(), "seed": 3}


def test_box_headline_preset_trains_two_passes_with_its_options_and_the_command_line_wins(tmp_path, capsys):
    data = make_dataset(tmp_path / "d", size=64, labelled=4, unlabelled=4, test=2)
    run = tmp_path / "run"
    args = ["train", str(data), "--out", str(run), "--preset", "box-headline", "--steps", "2",
            "--coarse-steps", "2", "--coarse-size", "32", "--crop-size", "32", "--channels", "8,8",
            "--res_blocks", "1", "--val_every", "0", "--warmup_steps", "1", "--ramp_steps", "1",
            "--no-progress", "--threads", "1", "--sigma", "1.5"]
    assert cli.main(args) == 0
    assert (run / "two_pass.json").is_file()  # the preset is a two-pass one
    coarse = json.loads((run / "coarse" / "config.json").read_text())["config"]
    fine = json.loads((run / "fine" / "config.json").read_text())["config"]
    preset = PRESETS["box-headline"].config
    assert coarse["rotation_deg"] == PRESETS["box-headline"].config.passes.coarse_rotation
    assert fine["rotation_deg"] == preset.augmentation.rotation_deg
    assert fine["layout_tol"] == preset.self_supervision.layout_tol
    assert fine["steps"] == 2 and coarse["steps"] == 2  # the command line's, not the preset's 2500 / 4000
    assert (coarse["lr"], fine["lr"]) == (PRESETS["box-headline"].config.passes.coarse_lr, preset.schedule.lr)
    assert fine["sigma"] == 1.5  # given on the command line
    proc = subprocess.run([sys.executable, "-m", "s3k.cli", "train", str(data), "--out", str(tmp_path / "x"),
                           "--preset", "nope"], capture_output=True, text=True)
    assert proc.returncode == 2 and "box-headline" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_box_fast_preset_cuts_its_crops_with_its_margin_unless_the_command_line_gives_one(tmp_path):
    data = make_dataset(tmp_path / "d", size=64, labelled=4, unlabelled=4, test=2)
    tiny = ["--steps", "2", "--coarse-steps", "2", "--coarse-size", "32", "--crop-size", "32", "--channels",
            "8,8", "--res-blocks", "1", "--val-every", "0", "--warmup-steps", "1", "--ramp-steps", "1",
            "--no-progress", "--threads", "1"]
    margins = {}
    for name, extra in (("preset", []), ("given", ["--crop-margin", "0.25"])):
        run = tmp_path / name
        assert cli.main(["train", str(data), "--out", str(run), "--preset", "box-fast", *tiny, *extra]) == 0
        margins[name] = json.loads((run / "two_pass.json").read_text())["margin"]
    assert margins == {"preset": PRESETS["box-fast"].config.passes.crop_margin, "given": 0.25}
    # the same network, schedule and coarse pass as the headline: only the crops differ
    headline = PRESETS["box-headline"].config
    assert PRESETS["box-fast"].config.replace(crop_size=headline.passes.crop_size,
                                              crop_margin=headline.passes.crop_margin) == headline


def test_real_pretrained_preset_is_the_headline_without_its_layout_on_the_pretrained_encoder():
    """The configuration measured on the real recording (docs/results/accuracy/pretrained): the headline's,
    with ``--layout-tol 0`` and the encoder cut at 8, at a tenth of each pass's learning rate."""
    chosen, headline = PRESETS["real-pretrained"].config, PRESETS["box-headline"].config
    assert (chosen.backbone.encoder, chosen.backbone.encoder_stride, chosen.backbone.encoder_lr,
            chosen.backbone.pretrained) == ("efficientnet-lite0", 8, 0.1, True)
    assert chosen.self_supervision.layout_tol == 0
    assert chosen.replace(encoder="unet", encoder_stride=headline.backbone.encoder_stride, encoder_lr=1.0,
                          layout_tol=headline.self_supervision.layout_tol) == headline


def test_the_two_pass_options_are_the_configurations_fields_with_their_ranges(capsys):
    """``s3k train --help`` lists the two-pass options in the configuration's own group, and a value out of a
    field's range is refused as the command line is parsed, naming the option."""
    import argparse

    from s3k.cli.train import configure_parser
    from s3k.config import TwoPassConfig, leaf_fields

    parser = argparse.ArgumentParser()
    configure_parser(parser)
    fields = [f.name for _, f, _ in leaf_fields(TwoPassConfig)]
    shown = {a.dest: a for a in parser._actions if a.help != argparse.SUPPRESS}
    assert set(fields) <= set(shown)
    assert shown["coarse_size"].type.range.ge == 16 and shown["crop_margin"].type.range.ge == 0
    for argv, option in ((["--coarse-size", "8"], "--coarse-size"), (["--crop-extent", "0"], "--crop-extent"),
                         (["--coarse-lr", "2"], "--coarse-lr")):
        with pytest.raises(SystemExit) as exc:
            parser.parse_args(["data", "--out", "run", *argv])
        assert exc.value.code == 2 and option in capsys.readouterr().err
    args = parser.parse_args(["data", "--out", "run", "--two-pass", "--coarse-steps", "none"])
    assert args.two_pass is True and args.coarse_steps is None


def test_box_precise_preset_is_the_headline_on_256_px_crops():
    """The configuration measured in docs/results/accuracy/crops-256: the headline's, crops of 256 px."""
    chosen, headline = PRESETS["box-precise"].config, PRESETS["box-headline"].config
    assert chosen.passes.crop_size == 256 and headline.passes.crop_size == 192
    assert chosen.replace(crop_size=headline.passes.crop_size) == headline
