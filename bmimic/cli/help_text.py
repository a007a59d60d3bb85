"""The text of `python -m bmimic.train --help`: config groups with their options, top-level keys with docs.

Hydra's own help lists the `*_schema` entries of the ConfigStore as options and prints the whole
composed config. conf/train.yaml sets `hydra.help.template: ${bmimic.help:}` instead; that resolver
(registered in bmimic/config/__init__.py) calls `train_help`, which lists each group's selectable options
(schemas left out, the current choice starred) and every top-level key with its current value and
the docstring its schema dataclass carries. Overrides on the command line show in the values and
choices: `python -m bmimic.train --help motion=lafan_dance1`.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import re
import shutil
import textwrap
from typing import Any, cast

SCHEMA_SUFFIX = "_schema"

EXTRA_GROUPS = {
    "sweep": "A study from sweeps/, run with -m: python -m bmimic.train -m +sweep=NAME.",
    "hydra/launcher": "How -m runs a sweep's jobs: one at a time (basic), several per machine "
                      "(joblib_gpus, needs the `parallel` extra) or on SLURM (slurm, the `slurm` extra).",
}
"""Groups that are not fields of the TrainConfig schema, with what they are for."""


def field_docs(cls: type) -> dict[str, str]:
    """{field: docstring} of a dataclass whose fields carry a string literal below them."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError):  # no source (frozen app): fields go undocumented
        return {}
    body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
    docs = {}
    for node, after in zip(body, body[1:]):
        if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)
                and isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)
                and isinstance(after.value.value, str)):
            docs[node.target.id] = " ".join(after.value.value.split())
    return docs


def _value(cfg: Any, key: str) -> str:
    from omegaconf import OmegaConf

    try:
        value = OmegaConf.select(cfg, key, throw_on_resolution_failure=True)
    except Exception:  # e.g. an interpolation that cannot be resolved here: show it as written
        value = cast(dict, OmegaConf.to_container(cfg, resolve=False)).get(key.split(".")[0])
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    return str(value)


def _wrapped(text: str, indent: int, width: int) -> str:
    return textwrap.fill(text, width=width, initial_indent=" " * indent, subsequent_indent=" " * indent)


def train_help(root: Any, schema: type, loader: Any = None) -> str:
    """The help text for the composed config `root` (with its `hydra` node) of the dataclass `schema`
    (bmimic.config.TrainConfig, which calls this); `loader` is Hydra's config loader (default: the
    running Hydra's)."""
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.object_type import ObjectType

    if loader is None:
        loader = GlobalHydra.instance().config_loader()
    width = max(60, min(110, shutil.get_terminal_size((100, 24)).columns))
    docs = field_docs(schema)
    try:
        choices = dict(root.hydra.runtime.choices)
    except Exception:  # composed without the hydra node
        choices = {}
    fields = {f.name: f for f in dataclasses.fields(schema) if f.name != "defaults"}
    # The loader's own listing copies its whole repository per call (Hydra 1.3): ask the repository.
    repository = getattr(loader, "repository", None)
    lister: Any = repository if hasattr(repository, "get_group_options") else loader
    top_groups = set(lister.get_group_options("", ObjectType.GROUP))
    groups = [g for g in fields if g in top_groups]
    lines = [
        "python -m bmimic.train [group=option ...] [key=value ...]: train a motion-tracking policy.",
        "",
        "  python -m bmimic.train sampler=uniform seed=3 motion=lafan_dance1",
        "  python -m bmimic.train -m +sweep=sampler_ablation        # a sweep (-m) from sweeps/",
        "  python -m bmimic.train --cfg job sampler=beyondmimic     # print the composed config",
        "",
        "== Config groups: group=option (* = current choice) ==",
    ]
    for group in [*groups, *EXTRA_GROUPS]:
        options = sorted(o for o in lister.get_group_options(group, ObjectType.CONFIG) if not o.endswith(SCHEMA_SUFFIX))
        if not options:
            continue
        current = choices.get(group)
        shown = ", ".join(f"{o}*" if o == current else o for o in options)
        prefix = "+sweep" if group == "sweep" else group
        lines.append(textwrap.fill(f"{prefix}: {shown}", width=width, subsequent_indent="    "))
        doc = re.sub(r"\s*\(group `[\w/]+`\)", "", docs.get(group) or EXTRA_GROUPS.get(group, ""))
        if doc:
            lines.append(_wrapped(doc, 4, width))
    lines += ["", "== Top-level keys: key=value (current value shown) =="]
    for name in fields:
        if name in groups:
            continue
        if _is_node(root, name):  # a plain node such as `data`: its keys, with its schema's docs
            entries = [(f"{name}.{sub}", doc) for sub, doc in _node_docs(schema, name, root[name]).items()]
        else:
            entries = [(name, docs.get(name, ""))]
        for key, doc in entries:
            lines.append(f"{key}={_value(root, key)}")
            if doc:
                lines.append(_wrapped(doc, 4, width))
    lines += [
        "",
        "Every other key is group.key=value (e.g. sampler.gamma=0.9, env.rewards.action_rate.weight=0);",
        "--cfg job prints them all. --hydra-help: Hydra's own options (hydra.run.dir=..., --multirun, ...).",
    ]
    return "\n".join(lines)


def _is_node(root: Any, name: str) -> bool:
    from omegaconf import OmegaConf

    # (not root.get(name): that resolves a value, and `seed=${oc.env:UNSET}` would end --help in a traceback)
    return isinstance(cast(dict, OmegaConf.to_container(root, resolve=False)).get(name), dict)


def _node_docs(schema: type, name: str, node: Any) -> dict[str, str]:
    """{key: doc} of the top-level node `name`, docs from its schema dataclass (e.g. DataConfig)."""
    (f,) = [f for f in dataclasses.fields(schema) if f.name == name]
    default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
    docs = field_docs(type(default)) if dataclasses.is_dataclass(default) else {}
    return {key: docs.get(key, "") for key in node}
