"""Every command's ``--help``, read from the command registry (``s3k.cli.COMMANDS``) and each command's
subcommands: options in one spelling, with dashes; the defaults stated; examples that parse. A training
field's own name (``--rotation_deg``) still works on the command line, as an alias that help does not show."""

from __future__ import annotations

import argparse
import dataclasses
import functools
import re
import shlex

import pytest

from s3k.cli import COMMANDS, command_parser, main
from s3k.config import TrainConfig, leaf_fields

UNDERSCORE_OPTION = re.compile(r"--[a-z0-9][a-z0-9-]*_")  # --rotation_deg, --no-layout_fit
FLAGS = (argparse._StoreTrueAction, argparse._StoreFalseAction, argparse.BooleanOptionalAction,
         argparse._HelpAction)


@functools.cache
def _parser(name: str) -> argparse.ArgumentParser:
    return command_parser(name)


def _commands() -> list[tuple[str, ...]]:
    """Every command and subcommand as the words that name it, e.g. ("robot", "grasp")."""
    out: list[tuple[str, ...]] = []
    for name in COMMANDS:
        out.append((name,))
        for action in _parser(name)._actions:
            if isinstance(action, argparse._SubParsersAction):
                out += [(name, sub) for sub in action.choices]
    return out


def _parser_of(words: tuple[str, ...]) -> argparse.ArgumentParser:
    parser = _parser(words[0])
    for word in words[1:]:
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = sub.choices[word]
    return parser


def _help(argv: list[str], capsys, monkeypatch, columns: int = 1000) -> str:
    """What ``s3k ARGV --help`` prints, on a terminal ``columns`` wide (wide: no option split by wrapping)."""
    monkeypatch.setenv("COLUMNS", str(columns))
    with pytest.raises(SystemExit) as exit_:
        main([*argv, "--help"])
    assert exit_.value.code in (0, None)
    return capsys.readouterr().out


COMMAND_WORDS = _commands()


def test_the_registry_is_read():
    assert len(COMMAND_WORDS) > len(COMMANDS) >= 10  # the commands and the subcommands of `s3k robot`
    assert ("train",) in COMMAND_WORDS and ("robot", "grasp") in COMMAND_WORDS


@pytest.mark.parametrize("words", COMMAND_WORDS, ids=" ".join)
def test_help_spells_options_with_dashes_and_names_an_example(words, capsys, monkeypatch):
    text = _help(list(words), capsys, monkeypatch)
    assert text.startswith(f"usage: s3k {' '.join(words)}")
    assert UNDERSCORE_OPTION.findall(text) == [], f"s3k {' '.join(words)} --help"
    assert "example" in text.lower(), f"s3k {' '.join(words)} --help names no example"


def test_top_level_help_names_an_example(capsys, monkeypatch):
    text = _help([], capsys, monkeypatch)
    assert "example" in text.lower() and UNDERSCORE_OPTION.findall(text) == []
    assert all(f"  {name} " in text for name in COMMANDS)


@pytest.mark.parametrize("words", COMMAND_WORDS, ids=" ".join)
def test_every_option_is_dashed_and_states_its_default(words):
    parser = _parser_of(words)
    for action in parser._actions:
        if not action.option_strings:
            continue
        if action.help == argparse.SUPPRESS:  # a hidden alias: the field's own name, for the shown option
            shown = {s for a in parser._actions if a.help != argparse.SUPPRESS for s in a.option_strings}
            assert getattr(action, "alias_of", None) in shown, action.option_strings
            continue
        assert not any("_" in s for s in action.option_strings), action.option_strings
        default = action.default
        if isinstance(action, FLAGS) or action.required or default is None or default is False \
                or default == argparse.SUPPRESS or default == []:
            continue
        text = parser._get_formatter()._expand_help(action)
        assert "default" in text.lower(), f"s3k {' '.join(words)} {action.option_strings[0]}: {text}"


def _example_lines(text: str) -> list[str]:
    lines = text.split("examples:\n", 1)[1].splitlines()
    return [line.strip() for line in lines if line.startswith("  ")]


@pytest.mark.parametrize("words", COMMAND_WORDS, ids=" ".join)
def test_the_examples_parse(words):
    """Each example of a command's help uses options that exist, with values they accept."""
    examples = _example_lines(_parser_of(words).epilog or "")
    assert examples, words
    for line in examples:
        argv = shlex.split(line.split(" > ")[0])
        assert argv[:len(words) + 1] == ["s3k", *words], line
        _parser(words[0]).parse_args(argv[2:])  # a refused option exits


def test_the_top_level_examples_parse(capsys, monkeypatch):
    for line in _example_lines(_help([], capsys, monkeypatch)):
        argv = shlex.split(line)
        assert argv[0] == "s3k" and argv[1] in COMMANDS, line
        _parser(argv[1]).parse_args(argv[2:])


def test_examples_are_printed_as_written_and_prose_is_wrapped(capsys, monkeypatch):
    text = _help(["stream"], capsys, monkeypatch, columns=60)
    for line in _example_lines(_parser("stream").epilog):
        assert f"\n  {line}\n" in text or text.endswith(f"  {line}\n")  # longer than 60, kept on one line
    description = text.split("\n\n")[1]
    assert max(len(line) for line in description.splitlines()) <= 60


def test_a_field_has_one_option_shown_and_its_own_name_as_hidden_alias(capsys, monkeypatch):
    from s3k.cli.config_options import config_from_args

    parser = _parser("train")
    base = ["D", "--out", "R"]
    dashed = parser.parse_args(base + ["--rotation-deg", "15", "--no-layout-fit", "--batch-labelled", "2"])
    aliases = parser.parse_args(base + ["--rotation_deg", "15", "--no-layout_fit", "--batch_labelled", "2"])
    assert config_from_args(dashed, TrainConfig) == config_from_args(aliases, TrainConfig)
    cfg = config_from_args(aliases, TrainConfig)
    assert cfg.augmentation.rotation_deg == 15.0 and cfg.schedule.batch_labelled == 2
    assert cfg.self_supervision.layout_fit is False
    flag = config_from_args(parser.parse_args(base + ["--layout_fit"]), TrainConfig)
    assert flag.self_supervision.layout_fit is True
    # an abbreviation of a field matches the option, not two spellings of it
    abbreviated = config_from_args(parser.parse_args(base + ["--rot", "20"]), TrainConfig)
    assert abbreviated.augmentation.rotation_deg == 20.0
    text = _help(["train"], capsys, monkeypatch)
    assert "--rotation-deg FLOAT" in text and "--layout-fit | --no-layout-fit" in text
    assert "--rotation_deg" not in text and "--no-layout_fit" not in text


def test_a_value_refused_names_the_spelling_given(capsys):
    for option in ("--rotation-deg", "--rotation_deg"):
        with pytest.raises(SystemExit):
            main(["train", "D", "--out", "R", option, "-1"])
        err = capsys.readouterr().err
        assert f"argument {option}: must be >= 0" in err and len(err.strip().splitlines()) == 1


def test_the_option_a_resume_hint_gives_is_dashed_and_parses():
    from s3k.cli.config_options import config_from_args
    from s3k.train.out_folder import _option

    assert _option("layout_tol", 0.2) == "--layout-tol 0.2"
    assert _option("layout_fit", False) == "--no-layout-fit"
    assert _option("channels", [8, 16]) == "--channels 8,16"
    argv = ["D", "--out", "R", *shlex.split(_option("rotation_deg", 15.0)), _option("unsup", False)]
    cfg = config_from_args(_parser("train").parse_args(argv), TrainConfig)
    assert (cfg.augmentation.rotation_deg, cfg.self_supervision.unsup) == (15.0, False)



def test_train_help_shows_every_configuration_field_with_its_range(capsys, monkeypatch):
    """The two-pass options come from TrainConfig's passes section like every other field, and each bounded
    field's help states its range, as the parser enforces it."""
    text = _help(["train"], capsys, monkeypatch)
    lines: dict[str, str] = {}  # each option's whole entry, its help wrapped onto the following lines too
    flag = ""
    for line in text.splitlines():
        if line.strip().startswith("--"):
            flag = line.split()[0].rstrip(",")
            lines[flag] = line
        elif flag and line.startswith("      "):
            lines[flag] += " " + line.strip()
        else:
            flag = ""
    assert "passes" in {f.name for f in dataclasses.fields(TrainConfig)}
    shown = 0
    for _, f, _ in leaf_fields(TrainConfig):
        flag = f"--{f.name.replace('_', '-')}"
        assert flag in lines, flag
        bounds = f.metadata.get("range")
        if bounds is not None and bounds.describe():
            assert f"; {bounds.describe()})" in lines[flag], (flag, lines[flag])
            shown += 1
    assert shown > 10
    for flag in ("--coarse-size", "--coarse-steps", "--coarse-stride", "--crop-size", "--crop-margin"):
        assert flag in lines
