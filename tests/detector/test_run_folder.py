"""The run folder has one owner: :class:`s3k.run_folder.RunFolder` names every file of a run, and no other
module of s3k spells one or parses a run's ``config.json``; it reads a run's configuration
(``tests/detector/test_old_runs.py``: older runs too)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from helpers.paths import REPO

from s3k.base.outputs import RUN_NAMES
from s3k.config import TrainConfig
from s3k.run_folder import RunFolder

PACKAGE = REPO / "s3k"
# a file name of a run as a string literal, or a pass's folder as a path part (``/ "coarse"``)
NAMES = ("config.json", "checkpoint.pt", "model.pt", "train.log", "progress.json", "tensorboard",
         "two_pass.json", "two_pass_options.json", "estimates.csv", "cpu.json")
_ALTERNATIVES = "|".join(re.escape(n) for n in NAMES)
PATTERN = re.compile(rf"""["'](?:[^"'\s]*/)?({_ALTERNATIVES})["']|/\s*["'](coarse|fine|crops)["']""")
# the robot's agents keep a run folder of their own kind (s3k.robot.agents), with its own config and progress
OWN_FOLDERS = {"robot/agents.py": {"config.json", "progress.json"}, "robot/results.py": {"progress.json"},
               "cli/robot.py": {"config.json"}}


# what a module holds the path of a run's config.json by: RunFolder's attributes, s3k.detector's name (the
# robot's agents name their own config.json ``config_file``, a plain name)
RECORD_ATTRIBUTES = {"config_file", "CONFIG", "CONFIG_FILE"}


def _names_a_record(node: ast.AST, aliases: set[str]) -> bool:
    return any(isinstance(n, ast.Attribute) and n.attr in RECORD_ATTRIBUTES
               or isinstance(n, ast.Name) and (n.id in aliases or n.id == "CONFIG_FILE")
               for n in ast.walk(node))


def record_parsers(tree: ast.AST) -> list[int]:
    """The lines where ``json.load``/``json.loads`` reads a run's ``config.json``: its path given directly, or
    through a name assigned from it."""
    aliases = {t.id for n in ast.walk(tree) if isinstance(n, ast.Assign) and _names_a_record(n.value, set())
               for t in n.targets if isinstance(t, ast.Name)}
    return sorted({n.lineno for n in ast.walk(tree)
                   if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute)
                   and n.func.attr in ("load", "loads") and isinstance(n.func.value, ast.Name)
                   and n.func.value.id == "json" and any(_names_a_record(a, aliases) for a in n.args)})


def test_no_module_but_run_folder_names_a_run_file_or_parses_its_record():
    found, parsed = [], []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel in ("run_folder.py", "base/run_files.py"):  # RunFolder and the RunFiles it builds on
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            for match in PATTERN.finditer(line):
                name = match.group(1) or match.group(2)
                if name not in OWN_FOLDERS.get(rel, set()):
                    found.append(f"s3k/{rel}:{number}: {name}")
        parsed += [f"s3k/{rel}:{n}" for n in record_parsers(ast.parse(path.read_text(), str(path)))]
    assert found == []
    assert parsed == [], "config.json is parsed by RunFiles alone (read_record, record, meta, dataset)"


def test_the_pattern_finds_names_as_the_code_would_spell_them():
    for line in ('x = run / "model.pt"', "p = Path(out) / 'coarse' / 'config.json'", 'f"{run}/train.log"'):
        assert PATTERN.search(line), line
    assert not PATTERN.search('"a coarse pass"') and not PATTERN.search("RunFolder.MODEL")
    parsing = ("json.loads(run.config_file.read_text())\n"
               "config = RunFolder(out).config_file\ndoc = json.loads(config.read_text())\n"
               "json.load(open(path / CONFIG_FILE))\njson.loads(cpu.read_text())\n")
    assert record_parsers(ast.parse(parsing)) == [1, 3, 4]


def test_run_folder_knows_every_file_and_the_output_checks_use_them():
    assert RUN_NAMES == set(RunFolder.ONE_PASS_FILES + RunFolder.TWO_PASS_FILES)
    assert {RunFolder.CONFIG, RunFolder.MODEL, RunFolder.TWO_PASS, RunFolder.ESTIMATES} <= RUN_NAMES
    run = RunFolder("runs/box")
    assert run.fine.checkpoint == Path("runs/box/fine/checkpoint.pt")
    assert run.coarse.config_file.parent == run.coarse.path == Path("runs/box/coarse")
    assert isinstance(run.fine, RunFolder) and isinstance(run.first_pass(), RunFolder)  # each has .config()


def test_a_run_folder_reads_its_configuration(tmp_path):
    run = RunFolder(tmp_path / "run")
    assert run.config() is None and not run.is_complete() and not run.is_two_pass_run()
    run.path.mkdir()
    cfg = TrainConfig.from_flat(two_pass=True, crop_size=64, coarse_rotation=90.0, steps=7)
    run.write_config(cfg)
    assert run.config() == cfg and run.is_two_pass_run() and run.is_stub() and not run.is_complete()
    run.write_cpu({"coarse": 1.5})
    assert run.read_cpu() == {"coarse": 1.5} and run.is_stub()
