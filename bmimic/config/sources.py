"""Where a command line says its config comes from (`-cp/--config-path`, `-cn/--config-name`,
`-cd/--config-dir`), checked before Hydra runs: Hydra reports a missing folder or primary config in a
multi-line block and exit status 1; bmimic's refusal is one line and exit status 2.

The search mirrors Hydra's (hydra._internal.utils.compute_search_path_dir): an absolute config path is a
folder, a relative one is relative to the folder of the module that declares the app (bmimic/, where
`python -m bmimic.train` and the console script both look), `pkg://` paths are Hydra's to resolve; the
primary config is `<name>.yaml` in the config path or in a `--config-dir`, or a config registered in
Hydra's ConfigStore.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

from bmimic import CONF_DIR
from bmimic.config import ConfigError, _hydra_args

APP_DIR = Path(__file__).resolve().parents[1]
"""The folder of bmimic.train, which declares the Hydra app: a relative --config-path starts there."""


def _folder(flag: str, value: str, base: Path | None) -> Path | None:
    """The folder `value` names (None for a `pkg://` path, Hydra's to find); ConfigError when it is none."""
    if value.startswith("pkg://"):
        import importlib.util

        top = value.removeprefix("pkg://").split("/")[0].split(".")[0]
        if not top or importlib.util.find_spec(top) is None:  # (a top-level name: nothing is imported to look)
            raise ConfigError(f"{flag} {value[:80]}: no such Python package")
        return None  # a package's configs: Hydra's to find
    text = value.removeprefix("file://")
    path = Path(text) if os.path.isabs(text) or base is None else base / text
    try:
        found = path.is_dir()
    except OSError:  # a name too long to look up, a loop of links
        found = False
    if not found:
        shown = value if len(value) <= 80 else f"{value[:60]}..."
        raise ConfigError(f"{flag} {shown}: no such folder{'' if path == Path(text) else f' ({path})'}")
    return path


def _registered(name: str) -> bool:
    """A primary config of that name in Hydra's ConfigStore (bmimic's schemas register there)."""
    from hydra.core.config_store import ConfigStore

    from bmimic.config import register_configs

    register_configs()
    try:
        ConfigStore.instance().load(f"{name}.yaml")
    except Exception:  # noqa: BLE001 - Hydra's ConfigLoadError and its relatives: not there
        return False
    return True


def check_config_source(argv: Sequence[str], config_name: str = "train") -> None:
    """ConfigError (one line) when `argv` names a config folder that does not exist (--config-path,
    --config-dir) or a primary config (--config-name; default `config_name`) found in none of the folders
    Hydra would search. A command line argparse refuses is left to Hydra's parser (its usage line)."""
    args = _hydra_args(list(argv))
    if args is None:
        return
    primary = CONF_DIR if args.config_path is None else _folder("--config-path", args.config_path, APP_DIR)
    extra = None if args.config_dir is None else _folder("--config-dir", args.config_dir, Path.cwd())
    if args.config_name is None and args.config_path is None:
        return  # bmimic's own tree and primary config
    if primary is None:
        return  # a package's configs: Hydra's to find
    name = args.config_name or config_name
    file = name if name.endswith(".yaml") else f"{name}.yaml"
    folders = [f for f in (primary, extra) if f is not None]
    try:
        found = any((f / file).is_file() for f in folders)
    except OSError:
        found = False
    if not found and not _registered(name.removesuffix(".yaml")):
        where = " or ".join(str(f) for f in folders)
        raise ConfigError(f"--config-name {name}: no {file} in {where} (bmimic's primary config is train)")


__all__ = ["check_config_source"]
