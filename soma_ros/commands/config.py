"""`soma config`: the config reference and resolved configs.

    soma config show train/tiny        # the file with its bases applied, as YAML
    soma config doc [--out FILE]        # the reference (docs/configuration.md), from the code
    soma config doc --check FILE        # exit 1 if FILE differs from the code's reference

The reference is generated from the config dataclasses themselves: every section, key,
type and default, with the comment written beside the field in the source. A test keeps
``docs/configuration.md`` equal to it.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import inspect
import re
import sys
import typing
from pathlib import Path
from typing import Any, Iterator

from . import documented_parser

#: (title, config folder, "module:Class", one line on where the file is used)
FAMILIES: list[tuple[str, str, str, str]] = [
    ("Training", "config/train", "soma_ros.training.config:TrainConfig", "`soma train --config NAME`"),
    ("Model", "config/models", "soma_ros.core.config:ModelConfig", "`model:` of a training config"),
    ("Object", "config/objects", "soma_ros.core.config:ObjectConfig", "per-object hierarchy and graph radii"),
    ("Evaluation", "config/eval", "soma_ros.evaluation.evaluate:EvalConfig", "`soma eval`, `soma bench accuracy`"),
    ("Accuracy benchmark", "(preset)", "soma_ros.evaluation.accuracy:BenchConfig", "`soma bench accuracy --preset NAME`"),
    ("Discrepancy workflow", "config/discrepancy", "soma_ros.discrepancy.workflow:DiscrepancyConfig", "`soma discrepancy`"),
    ("Robot", "config/robots", "soma_ros.core.robot_config:RobotConfig", "`robot:` of a training config, the node"),
    ("Reference world", "config/world", "soma_ros.world.config:WorldConfig", "`soma world --config NAME`"),
]

HEADER = """# Configuration reference

Generated from the config dataclasses by `soma config doc`; `test/commands/test_config_doc.py`
keeps this page equal to the code. Every config is a YAML file loaded strictly into
these dataclasses: an unknown key or a value of the wrong type is an error that names
the key.

A variant names its base and writes only what differs:

```yaml
base: tiny          # config/train/tiny.yaml, merged key by key (lists are replaced)
schedule:
  iterations: 360
```

`soma config show train/NAME` prints a config with its bases applied.

## Defaults that differ between layers

- **Passive-object rule**: off in the core (`dynamics.passive_friction: null`), so in training
  and evaluation, because every model is trained and scored as it predicts; on in the node
  (`passive_friction: 0.5`) and the discrepancy workflow, which run a trained model open-ended
  beside a robot, where a learned model's small spurious forces would otherwise add up.
- **Settling**: never in the engine (`LiveSimulator(settle_s=0)`, so in `soma resim` and `soma
  eval`: a rollout is scored as predicted); after 2 s in the node (`settle_time_s`), which runs
  without end.
- **Robot coupling**: the `robot` effect's `form` defaults to `mlp`, the paper's free-form
  module, so the `cpu` and `paper` model configs are the paper's model and older checkpoints
  load unchanged; the shipped `tiny*` training configs select `form: coupling`, which learns in
  a CPU budget (docs/design_decisions.md).
"""


def _load(target: str) -> type:
    module, name = target.split(":")
    return getattr(importlib.import_module(module), name)


def _type_name(tp: Any) -> str:
    if isinstance(tp, str):
        return tp
    origin = typing.get_origin(tp)
    if origin is None:
        return getattr(tp, "__name__", str(tp)).replace("NoneType", "None")
    args = [a for a in typing.get_args(tp)]
    if origin is typing.Union:
        parts = [_type_name(a) for a in args if a is not type(None)]
        text = " | ".join(parts)
        return f"{text} | None" if type(None) in args else text
    name = getattr(origin, "__name__", str(origin))
    return f"{name}[{', '.join(_type_name(a) for a in args)}]"


def _field_comments(cls: type) -> dict[str, str]:
    """The ``# comment`` written on (or right under) each field line of ``cls``'s body."""
    try:
        lines = inspect.getsource(cls).splitlines()
    except (OSError, TypeError):
        return {}
    out: dict[str, str] = {}
    names = {f.name for f in dataclasses.fields(cls)}
    current = None
    for line in lines[1:]:
        m = re.match(r"^    (\w+)\s*:\s*[^=#]+(?:=[^#]*)?(?:#\s?(.*))?$", line)
        if m and m.group(1) in names:
            current = m.group(1)
            if m.group(2):
                out[current] = m.group(2).strip()
            continue
        cont = re.match(r"^\s{4,}#\s?(.*)$", line)
        if cont and current is not None and current in out:
            out[current] += " " + cont.group(1).strip()
        else:
            current = None
    return out


def _doc_meanings(cls: type) -> dict[str, str]:
    """Per key, the text the class docstring gives it (``key``: text, up to the next key)."""
    doc = " ".join((inspect.getdoc(cls) or "").split())
    out: dict[str, str] = {}
    keys = r"``(\w+)``(?:\s*(?:/|,|and)\s*``\w+``)*"
    for m in re.finditer(keys + r":\s", doc):
        names = re.findall(r"``(\w+)``", m.group(0))
        rest = doc[m.end():]
        nxt = re.search(r"\s" + keys + r":\s", rest)
        text = (rest[: nxt.start()] if nxt else rest).strip()
        for name in names:
            out.setdefault(name, text)
    return out


def _default(f: dataclasses.Field) -> str:
    if f.default is not dataclasses.MISSING:
        value = f.default
    elif f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        value = f.default_factory()  # type: ignore[misc]
        if dataclasses.is_dataclass(value):
            return "(section)"
    else:
        return "required"
    if isinstance(value, list) and value and dataclasses.is_dataclass(value[0]):
        return f"{len(value)} entries"
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _sections(cls: type, prefix: str) -> Iterator[tuple[str, type]]:
    yield prefix, cls
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints.get(f.name, f.type)
        if isinstance(tp, type) and dataclasses.is_dataclass(tp):
            yield from _sections(tp, f"{prefix}.{f.name}" if prefix else f.name)


def _doc(cls: type) -> str:
    """The first paragraph of the class docstring."""
    doc = inspect.getdoc(cls) or ""
    if doc.startswith(cls.__name__ + "("):  # dataclass auto-doc
        return ""
    return " ".join(doc.split("\n\n")[0].split())


def reference() -> str:
    """The whole reference page (markdown)."""
    out = [HEADER]
    for title, folder, target, used in FAMILIES:
        cls = _load(target)
        out.append(f"\n## {title}\n\nFiles: `{folder}/*.yaml`; used by {used}. Class `{target.replace(':', '.')}`.\n")
        for prefix, sec in _sections(cls, ""):
            hints = typing.get_type_hints(sec)
            heading = f"`{prefix}`" if prefix else "top level"
            out.append(f"\n### {title}: {heading}\n")
            intro = _doc(sec)
            if intro:
                out.append(f"\n{intro}\n")
            comments = {**_doc_meanings(sec), **_field_comments(sec)}
            out.append("\n| key | type | default | meaning |\n|---|---|---|---|\n")
            for f in dataclasses.fields(sec):
                tp = hints.get(f.name, f.type)
                if isinstance(tp, type) and dataclasses.is_dataclass(tp):
                    meaning = f"section, below: `{prefix + '.' if prefix else ''}{f.name}`"
                else:
                    meaning = comments.get(f.name, "")
                cell = meaning.replace("|", "\\|")
                out.append(f"| `{f.name}` | `{_type_name(tp)}` | `{_default(f)}` | {cell} |\n")
    return "".join(out)


def register(subparsers) -> None:
    p = documented_parser(subparsers, "config", "the config reference and resolved configs", __doc__)
    sub = p.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    show = sub.add_parser("show", help="print a config with its bases applied")
    show.add_argument("name", help="a path, or FAMILY/NAME under config/ (e.g. train/tiny)")
    doc = sub.add_parser("doc", help="write the configuration reference")
    doc.add_argument("--out", default=None, help="file to write (default: standard output)")
    doc.add_argument("--check", default=None, metavar="FILE", help="exit 1 if FILE differs from the reference")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.config_command == "show":
        import yaml

        from ..core.config import read_config
        from ..paths import resolve_config

        print(yaml.safe_dump(read_config(resolve_config(args.name)), sort_keys=False), end="")
        return 0
    text = reference()
    if args.check:
        current = Path(args.check).read_text() if Path(args.check).is_file() else ""
        if current != text:
            print(f"soma config doc: {args.check} differs from the code; run `soma config doc --out {args.check}`",
                  file=sys.stderr)
            return 1
        return 0
    if args.out:
        Path(args.out).write_text(text)
    else:
        sys.stdout.write(text)
    return 0
