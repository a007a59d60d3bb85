"""The README's commands are the ones that work: CI's command, the override examples, the main run."""

from __future__ import annotations

import re
import shlex

import pytest

from bmimic.sampling.config import variant_names
from tests.conftest import REPO, compose

README = (REPO / "README.md").read_text()
GUIDE = (REPO / "docs" / "guide.md").read_text()
"""The user's guide: the README's sections past its first screen, whose commands are held as the README's."""


def code_lines() -> list[str]:
    """Command lines of the README's bash blocks, then the guide's, with continuations joined and comments
    removed."""
    lines = []
    for block in re.findall(r"```bash\n(.*?)```", README + "\n" + GUIDE, flags=re.S):
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
    section = README.split("## Set-up", 1)[1].split("\n## ", 1)[0]
    assert section.index("download.pytorch.org/whl/cpu") < section.index("```bash")  # the CPU note comes first
    assert "These two commands are the whole set-up" in section
    ci = [line.strip() for line in (REPO / ".ci" / "run").read_text().splitlines()]
    assert install_and_test in ci, "the CI script must run the README's test command verbatim"


def test_ci_installs_into_a_fresh_venv_as_the_readme_says():
    lines = [line.strip() for line in (REPO / ".ci" / "run").read_text().splitlines()
             if line.strip() and not line.startswith("#")]
    commands = [c.strip() for line in lines for c in line.split("&&")]
    venv = next(i for i, c in enumerate(commands) if re.fullmatch(r"python3? -m venv \S+", c))
    assert "--system-site-packages" not in commands[venv]
    assert any(c.startswith("tmp=") and "mktemp -d" in c for c in commands[:venv])  # a temporary folder
    assert re.fullmatch(r"\. \"?\S+/bin/activate\"?", commands[venv + 1])
    torch = [i for i, c in enumerate(commands) if re.search(r"pip install.* torch\b", c)]
    test = commands.index(setup_commands()[1].split("&&")[0].strip())
    assert len(torch) == 1 and venv < torch[0] < test
    assert re.search(r"torch==\d", commands[torch[0]]), "never an unpinned torch: it pulls the CUDA build"
    assert venv < commands.index("ruff check .") < test and commands[-1] == "pytest"
    # nothing else is installed into the venv: what the tests need comes from the README's extras
    installs = [c for c in commands if c.startswith("pip install")]
    assert installs == ["pip install -q ruff", commands[torch[0]], setup_commands()[1].split("&&")[0].strip()]


TRAIN_EXAMPLES = [line for line in code_lines() if line.startswith("python -m bmimic.train") and "--" not in line
                  and "my_study" not in line]
"""(The README's own study needs its sweep file on a search path: tests/cli/test_own_study.py runs it.)"""


@pytest.mark.parametrize("line", TRAIN_EXAMPLES)
def test_readme_train_examples_compose(line):
    args = shlex.split(line)[3:]
    multirun = "-m" in args
    args = [a for a in args if a != "-m"]
    task = [a for a in args if not a.startswith("hydra")]  # motion=lafan_*: the clip is read when a run starts
    cfg = compose(task, return_hydra_config=multirun)
    assert cfg.sampler.name in variant_names()


# torchrun (one node or several; train or race) and the SLURM script: the overrides after the program.
MULTI_GPU_EXAMPLES = [re.split(r" -m bmimic\.(?:train|race) | sweeps/slurm_multinode\.sh ", line, maxsplit=1)[1]
                      for line in code_lines() if line.startswith(("torchrun ", "sbatch "))]


def test_readme_multi_gpu_examples_compose():
    assert len(MULTI_GPU_EXAMPLES) >= 3 and (REPO / "sweeps" / "slurm_multinode.sh").exists()
    for overrides in MULTI_GPU_EXAMPLES:
        compose([a for a in shlex.split(overrides) if not a.startswith("hydra")])


# The README's commands run, the first one exactly as written: tests/test_readme_commands.py (slow).
