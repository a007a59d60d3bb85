"""The README's commands are the ones that work: CI's command, the override examples, the main run."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys

import pytest

from tests.conftest import REPO, cli_env, compose

README = (REPO / "README.md").read_text()


def code_lines() -> list[str]:
    """Command lines of the README's bash blocks, with continuations joined and comments removed."""
    lines = []
    for block in re.findall(r"```bash\n(.*?)```", README, flags=re.S):
        block = block.replace("\\\n", " ")
        for line in block.splitlines():
            line = line.split("  #")[0].strip()
            if line:
                lines.append(line)
    return lines


def setup_commands() -> list[str]:
    section = README.split("## Set-up", 1)[1]
    block = re.search(r"```bash\n(.*?)```", section, flags=re.S).group(1)
    return [line.strip() for line in block.strip().splitlines()]


def test_two_setup_commands_and_ci_runs_the_second():
    install_and_run, install_and_test = setup_commands()
    assert install_and_run.endswith("python -m bmimic.train")
    assert "pytest" in install_and_test
    ci = (REPO / ".ci" / "run").read_text().splitlines()
    assert install_and_test in ci, "the CI script must run the README's test command verbatim"


TRAIN_EXAMPLES = [line for line in code_lines() if line.startswith("python -m bmimic.train") and "--" not in line]


@pytest.mark.parametrize("line", TRAIN_EXAMPLES)
def test_readme_train_examples_compose(line):
    args = shlex.split(line)[3:]
    multirun = "-m" in args
    args = [a for a in args if a != "-m"]
    task = [a for a in args if not a.startswith("hydra")]
    if any(a.startswith("motion=lafan") for a in task):
        pass  # composes without the data; the file is only read when a run starts
    cfg = compose(task, return_hydra_config=multirun)
    assert cfg.sampler.name in ("uniform", "adaptive", "beyondmimic")


@pytest.mark.slow
def test_readme_main_command_runs_on_cpu(tmp_path):
    """The README's first command, exactly, as a smoke-scale run (it says so when it starts)."""
    command = setup_commands()[0].split("&&")[1].strip()
    out = subprocess.run(shlex.split(command.replace("python", sys.executable, 1)), cwd=tmp_path,
                         capture_output=True, text=True, timeout=1200, env=cli_env())
    assert out.returncode == 0, out.stderr[-3000:]
    assert "smoke-scale run" in out.stderr + out.stdout
    runs = list((tmp_path / "outputs" / "runs" / "default").iterdir())
    assert len(runs) == 1 and (runs[0] / "metrics.json").exists()
    assert '"done"' in (runs[0] / "status.json").read_text()
