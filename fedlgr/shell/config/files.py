"""Config files: where the shipped ``conf/`` and ``sweeps/`` are, and reading one file, preceded by
what it ``includes``, as layers of settings; a path that is no config is refused in one line."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

from fedlgr.errors import ConfigError, first_line
from fedlgr.shell.checks.paths import not_a_file
from fedlgr.shell.config.written import plain


def _shipped(folder: str) -> Path:
    """``conf/`` or ``sweeps/``: the copy a wheel ships inside the package, else the checkout's next
    to the package."""
    package = Path(__file__).resolve().parents[2]  # fedlgr/
    return package / folder if (package / folder).is_dir() else package.parent / folder


CONF_DIR = _shipped("conf")
SWEEPS_DIR = _shipped("sweeps")

SETTING_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_.]{0,99}")

MAX_NESTING = 50  # levels of a config file (OmegaConf's recursion gives up at 90)


def find_config(name: str | Path) -> Path:
    """A config file as given, else the shipped one it names under ``conf/`` (``debug/fast.yaml``,
    ``.yaml`` optional); unchanged when neither exists."""
    path = Path(name)
    if path.is_file() or path.is_absolute():
        return path
    inside = Path(*path.parts[1:]) if path.parts[:1] == ("conf",) else path
    for candidate in (CONF_DIR / inside, (CONF_DIR / inside).with_suffix(".yaml")):
        if candidate.is_file():
            return candidate
    return path


def read_layers(path: Path, seen: tuple[Path, ...] = ()) -> list[tuple[Any, Any]]:
    """The YAML at ``path`` preceded by what it includes, each as ``(path, OmegaConf
    node)``; ``seen``: the files including it, outermost first."""
    path = _config_file(path, seen)
    node = _read_settings(path)
    layers: list[tuple[Any, Any]] = []
    for inc in _includes(node):
        if "${" in str(inc):
            raise ConfigError(f"{path}: includes: {inc!r}: name the file (no ${{...}} here)")
        layers += read_layers(_included(Path(str(inc)), path), (*seen, path))
    return [*layers, (path, node)]


def _config_file(path: Path, seen: tuple[Path, ...]) -> Path:
    """``path`` resolved, once it is known to be a regular file that is not already being
    read; else one line saying what it is instead."""
    # a broken link, a path under a FIFO or a file, a device or a pipe (/dev/stdin, before it
    # resolves to /proc/PID/fd/pipe:[N]): named for what it is, not "not found"; a read never ends
    if not path.is_dir() and (why := not_a_file(path)):
        raise ConfigError(f"{path.absolute()}: {why}")
    path = path.resolve()
    if path in seen:
        raise ConfigError(f"{path}: includes itself (via {' -> '.join(p.name for p in seen)})")
    if path.is_dir():
        raise ConfigError(f"{path}: a folder, not a config file (name a .yaml file in it)")
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    return path


def _read_settings(path: Path) -> Any:
    from omegaconf import OmegaConf  # lazy: fedlgr --help reads this module without OmegaConf

    _check_nesting(path)
    try:
        node = OmegaConf.load(path)
    except Exception as err:
        raise ConfigError(f"{path}: {yaml_reason(err)}") from err
    if node is None or not OmegaConf.is_dict(node):
        raise ConfigError(f"{path}: expected a mapping of settings at the top level")
    if len(node) == 0:  # an empty file would run every default without a word
        raise ConfigError(f"{path}: holds no settings (an empty file); give a config that does")
    if any(not SETTING_NAME.fullmatch(str(key)) for key in node):
        # e.g. a text file named as a config or a sweep's base: its text is not echoed
        raise ConfigError(
            f"{path}: not a config file: its top level is not `setting: value` lines "
            "(a setting name is letters, digits, _ and .)"
        )
    return node


def _includes(node: Any) -> list:
    """The names a layer ``includes`` (as written, nothing resolved), taken out of ``node``
    so that they are not read as a setting."""
    written = plain(node)  # nothing resolved
    includes = written.get("includes") or []
    if "includes" in written:
        del node["includes"]
    return includes if isinstance(includes, list) else [includes]


def _included(name: Path, including: Path) -> Path:
    """The file ``includes: [NAME]`` in ``including`` names: NAME.yaml (or NAME itself), relative to
    conf/, else to the including file. A suffix is added, never replaced, so ``cfg.fifo`` is not
    read as cfg.yaml."""
    names = [name] if name.suffix in (".yaml", ".yml") else [name.with_name(f"{name.name}.yaml")]
    names += [name] if name not in names else []
    folders = [Path("/")] if name.is_absolute() else [CONF_DIR, including.parent]
    candidates = [folder / n for n in names for folder in folders]
    return next((c for c in candidates if os.path.lexists(c)), candidates[len(folders) - 1])


def yaml_reason(err: Exception) -> str:
    """Why OmegaConf's loader refused a YAML file, in one line. Its limit on a file's nodes (against
    alias bombs) is said as what it is, without its advice to lift a safety limit."""
    first = first_line(err)
    found = re.search(r"YAML node expansion exceeds the configured limit of (\d+)", first)
    if found:
        return (
            f"too large: over {int(found.group(1)):,} YAML nodes (keys, values and list "
            "items), more than OmegaConf reads from one file (a config holds a few hundred)"
        )
    return f"not valid YAML ({first})"


def _check_nesting(path: Path) -> None:
    """A file nested deeper than MAX_NESTING levels is one line: libyaml's recursive composer
    crashes the process (SIGSEGV) on very deep nesting, so its event parser counts the levels."""
    import yaml  # lazy: fedlgr --help reads this module without yaml

    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    opened = (yaml.MappingStartEvent, yaml.SequenceStartEvent)
    closed = (yaml.MappingEndEvent, yaml.SequenceEndEvent)
    depth = 0
    try:
        with path.open("rb") as stream:
            for event in yaml.parse(stream, Loader=loader):
                if isinstance(event, opened):
                    depth += 1
                    if depth > MAX_NESTING:
                        line = event.start_mark.line + 1
                        raise ConfigError(
                            f"{path}: nested over {MAX_NESTING} levels deep (line {line}); "
                            "a config nests a few"
                        )
                elif isinstance(event, closed):
                    depth -= 1
    except (yaml.YAMLError, OSError, UnicodeDecodeError):
        return  # said with its reason by the load that follows
