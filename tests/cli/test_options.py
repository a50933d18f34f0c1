"""Every numeric option of every command is held to a range as the command line is parsed: finite, within
bounds, refused in one line before any work."""

from __future__ import annotations

import argparse
import importlib

import pytest

from s3k.cli import COMMANDS, _Parser, main


def _parsers() -> list[tuple[str, argparse.ArgumentParser]]:
    out = []
    for name, (module, _) in COMMANDS.items():
        parser = _Parser(prog=f"s3k {name}")
        importlib.import_module(f"s3k.cli.{module}").configure_parser(parser)
        out.append((f"s3k {name}", parser))
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                out += [(f"s3k {name} {sub}", p) for sub, p in action.choices.items()]
    return out


def _options(parser: argparse.ArgumentParser):
    return [a for a in parser._actions if a.option_strings and a.type is not None]


def test_no_numeric_option_is_parsed_without_a_range():
    unchecked = [f"{prog} {a.option_strings[0]}" for prog, parser in _parsers() for a in _options(parser)
                 if a.type in (int, float)]
    assert unchecked == []
    ranged = [a for _, parser in _parsers() for a in _options(parser) if hasattr(a.type, "range")]
    assert len(ranged) > 80  # the training configuration's fields and every command's own numbers


def test_every_numeric_option_refuses_nan_and_inf():
    for _, parser in _parsers():
        for action in _options(parser):
            if not hasattr(action.type, "range"):
                continue
            for text in ("nan", "inf", "-inf"):
                with pytest.raises(argparse.ArgumentTypeError, match="finite|int"):
                    action.type(text)


@pytest.mark.parametrize("argv, option", [
    (["label", "propagate", "D", "--frames", "0:3", "--max-changed", "nan"], "--max-changed"),
    (["label", "propagate", "D", "--frames", "0:3", "--max-changed", "-5"], "--max-changed"),
    (["check-calibration", "D", "--factor", "nan"], "--factor"),
    (["train", "D", "--out", "R", "--rotation-deg", "nan"], "--rotation-deg"),
    (["train", "D", "--out", "R", "--rotation_deg", "nan"], "--rotation_deg"),  # the field's name, an alias
    (["train", "D", "--out", "R", "--lr", "inf"], "--lr"),
    (["train", "D", "--out", "R", "--lr", "nan"], "--lr"),
    (["train", "D", "--out", "R", "--two-pass", "--crop-size", "0"], "--crop-size"),
    (["train", "D", "--out", "R", "--two-pass", "--crop-extent", "nan"], "--crop-extent"),
    (["export-tracks", "t.csv", "--format", "nwb", "--out", "t.nwb", "--fps", "inf"], "--fps"),
    (["simulate", "box", "--out", "D", "--workers", "-2"], "--workers"),
    (["validate", "D", "--workers", "-2"], "--workers"),
    (["evaluate", "R", "--data", "D", "--overlays", "-1"], "--overlays"),
    (["evaluate", "R", "--data", "D", "--batch-size", "0"], "--batch-size"),
    (["predict", "R", "--data", "D", "--out", "p.csv", "--batch-size", "0"], "--batch-size"),
    (["import", "--calibration", "c.toml", "--videos", "a=a.mp4", "--out", "D", "--units", ""], "--units"),
    (["import", "--calibration", "c.toml", "--videos", "a=a.mp4", "--out", "D", "--scale", "nan"], "--scale"),
    (["export", "R", "--format", "onnx", "--out", "d.onnx", "--opset", "1"], "--opset"),
    (["label", "D", "--port", "99999"], "--port"),
    (["robot", "train-agent", "--out", "A", "--learning-rate", "nan"], "--learning-rate"),
    (["train", "D", "--out", "R", "--device", "gpu"], "--device"),
    (["evaluate", "R", "--data", "D", "--device", "cuda:x"], "--device"),
    (["track", "R", "--calibration", "c.toml", "--videos", "a=a.mp4", "--out", "t.csv", "--device", "cuda1"],
     "--device"),
])
def test_bad_values_are_refused_in_one_line(argv, option, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and option in err and "error" in err
    assert list(tmp_path.iterdir()) == []  # refused before any work


def test_the_configuration_checks_its_fields_with_the_same_ranges():
    from s3k.base.errors import UserError
    from s3k.config import TrainConfig

    for field, value in (("lr", float("inf")), ("rotation_deg", float("nan")), ("steps", 0), ("seed", -1),
                         ("scale", 1.0)):
        with pytest.raises(UserError, match=f"'{field}'"):
            TrainConfig.from_flat(**{field: value}).validate()


def test_a_device_is_one_type_read_by_one_function_wherever_it_is_given(tmp_path):
    """``auto``, ``cpu``, ``cuda`` or ``cuda:N``: a config file and a configuration built in Python are held
    to the names the command line takes, each refusal one line naming the field or option."""
    from s3k.base.choices import parse_device
    from s3k.base.errors import UserError
    from s3k.config import ExecutionConfig, ModelConfig, TrainConfig, config_from_dict
    from s3k.config_files import read_config_file
    from s3k.detector import pick_device

    assert [parse_device(t) for t in ("auto", "cpu", "cuda", "cuda:12")] == ["auto", "cpu", "cuda", "cuda:12"]
    for text in ("gpu", "cuda:", "cuda:-1", "cuda:1 ", "CPU", 0):
        with pytest.raises(UserError, match="is not a device; pass auto, cpu, cuda or cuda:N"):
            parse_device(text)
    config = tmp_path / "c.json"
    config.write_text('{"device": "gpu"}')
    with pytest.raises(UserError, match=f"config file {config}: field 'device': 'gpu' is not a device"):
        config_from_dict(TrainConfig, read_config_file(config), where=f"config file {config}")
    assert TrainConfig.from_flat(device="cuda:1").execution.device == "cuda:1"
    with pytest.raises(UserError, match="--device: 'gpu' is not a device"):
        pick_device("gpu")  # type: ignore[arg-type]
    # a configuration built in Python: its choices checked as it is validated, like its ranges
    for cfg, name in ((TrainConfig(execution=ExecutionConfig(device="gpu")), "device"),  # type: ignore[arg-type]
                      (TrainConfig(execution=ExecutionConfig(precision="half")), "precision"),  # type: ignore
                      (TrainConfig(model=ModelConfig(norm="layer")), "norm")):  # type: ignore[arg-type]
        with pytest.raises(UserError, match=f"config field '{name}'"):
            cfg.validate()
