"""Command-line flags for the BouncingThingsConfig and LayersConfig fields: help from the field docstrings, strict
parsing.

Every field ``name`` becomes ``--name-with-dashes VALUE``. The help line of a flag is the field's
docstring (the string literal under the field in flowsynth/scene/config.py), its type and
its default in command-line form. A value that does not parse is refused by argparse with a message
that names the flag and the expected form (``argument --fov-deg: expected a number such as 60.0,
got 'abc'``), exit status 2.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import functools
import inspect
from typing import Any

__all__ = ["SIZE_FIELDS", "add_config_flags", "add_layers_flags", "cli_form", "docs_of", "field_docs", "flag_type",
           "integer", "layers_only_fields"]

SIZE_FIELDS = ("width", "height", "num_frames")
"""The config fields that set a sample's shape (``--width``, ``--height``, ``--num-frames``): every kind has them."""


@functools.cache
def field_docs() -> dict[str, str]:
    """{field name: its docstring} of BouncingThingsConfig, read from the source of flowsynth.scene.config."""
    from flowsynth.scene import BouncingThingsConfig

    return docs_of(BouncingThingsConfig)


def docs_of(config_class) -> dict[str, str]:
    """{field name: its docstring} of the dataclass ``config_class``, read from its module's source."""
    tree = ast.parse(inspect.getsource(inspect.getmodule(config_class)))
    cls = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == config_class.__name__)
    docs = {}
    for field, after in zip(cls.body, cls.body[1:]):
        if (isinstance(field, ast.AnnAssign) and isinstance(field.target, ast.Name)
                and isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)
                and isinstance(after.value.value, str)):
            docs[field.target.id] = inspect.cleandoc(after.value.value)
    return docs


def cli_form(value: Any) -> str:
    """A config value as it is typed on the command line: ``4,12`` for tuples, ``none`` for None."""
    if value is None:
        return "none"
    if isinstance(value, tuple):
        return ",".join(cli_form(v) for v in value)
    return str(value)


_BOOLS = {"true": True, "yes": True, "on": True, "1": True, "false": False, "no": False, "off": False, "0": False}


def _bool(text: str) -> bool:
    if text.lower() not in _BOOLS:
        raise ValueError(text)
    return _BOOLS[text.lower()]


_SCALARS = {"int": (int, "an integer"), "float": (float, "a number"), "str": (str, "text"),
            "bool": (_bool, "true or false")}


def _scalar(text: str, kind: str):
    return _SCALARS[kind][0](text.strip())


def integer(text: str) -> int:
    """argparse ``type=`` for plain integer flags (``--num``, ``--seed``, ...): names the expected form."""
    try:
        return int(text.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, such as 8; got {text!r}") from None


def flag_type(field: dataclasses.Field):
    """argparse ``type=`` for a config field: parses the command-line form, or explains the expected one."""
    t = (field.type if isinstance(field.type, str) else getattr(field.type, "__name__", str(field.type)))
    t = t.replace(" ", "")
    optional = "|None" in t or "None|" in t
    t = t.replace("|None", "").replace("None|", "")
    example = cli_form(field.default)
    if t.startswith("tuple["):
        inner = t[len("tuple["):-1].split(",")
        kind = inner[0]
        count = None if inner[-1] == "..." else len(inner)
        noun = {"int": "integers", "float": "numbers", "str": "names", "bool": "true/false values"}[kind]
        form = (f"{count} {noun} separated by commas" if count else f"{noun} separated by commas")
    else:
        kind, count = t, None
        form = _SCALARS[kind][1]
    if optional:
        form += " or none"
    form += f", such as {example}"

    def parse(text: str):
        if optional and text.strip().lower() in ("none", "null"):
            return None
        try:
            if t.startswith("tuple["):
                parts = [p.strip() for p in text.split(",") if p.strip() != ""]
                if count is not None and len(parts) != count:
                    raise ValueError(text)
                return tuple(_scalar(p, kind) for p in parts)
            return _scalar(text, kind)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {form}; got {text!r}") from None

    parse.__name__ = t
    if t.startswith("tuple["):
        parse.metavar = {2: "MIN,MAX", 3: "X,Y,Z"}.get(count) or {"int": "N,N,...", "float": "X,X,..."}.get(
            kind, "NAME,NAME,...")
    else:
        parse.metavar = kind.upper()
    if optional:
        parse.metavar += "|none"
    return parse


def _field_help(meaning: str, f: dataclasses.Field) -> str:
    """A config field flag's help: its docstring without markup, then its type and default."""
    meaning = " ".join(meaning.split()).replace("``", "").replace("%", "%%")
    return f"{meaning} [{str(f.type).replace(' ', '')}, default {cli_form(f.default)}]"


def add_config_flags(parser: argparse.ArgumentParser, *, documented: bool = True) -> None:
    """Add one flag per BouncingThingsConfig field (dest ``cfg_<name>``, default None = not given); with
    ``documented=False`` the flags parse as ever but stay out of ``--help`` (``--help-fields`` lists them)."""
    from flowsynth.scene import BouncingThingsConfig

    docs = field_docs()
    grp = parser.add_argument_group("scene configuration (BouncingThingsConfig fields; override --config)")
    for f in dataclasses.fields(BouncingThingsConfig):
        typ = flag_type(f)
        grp.add_argument("--" + f.name.replace("_", "-"), dest="cfg_" + f.name, default=None, type=typ,
                         metavar=typ.metavar,
                         help=_field_help(docs.get(f.name, ""), f) if documented else argparse.SUPPRESS)


def layers_only_fields() -> list[dataclasses.Field]:
    """The LayersConfig fields that are no BouncingThingsConfig field (the others share their flag)."""
    from flowsynth.datasets import LayersConfig
    from flowsynth.scene import BouncingThingsConfig

    shared = {f.name for f in dataclasses.fields(BouncingThingsConfig)}
    return [f for f in dataclasses.fields(LayersConfig) if f.name not in shared]


def add_layers_flags(parser: argparse.ArgumentParser, *, documented: bool = True) -> None:
    """Add one flag per LayersConfig field that is no BouncingThingsConfig field (dest ``layers_<name>``, default
    None = not given); the shared fields (width, height, num_frames, texture_dir) take the scene's flags.
    ``documented`` as in :func:`add_config_flags`."""
    from flowsynth.datasets import LayersConfig

    docs = docs_of(LayersConfig)
    grp = parser.add_argument_group("2D layers (--dataset layers; LayersConfig fields besides --width, --height, "
                                    "--num-frames and --texture-dir)")
    for f in layers_only_fields():
        typ = flag_type(f)
        grp.add_argument("--" + f.name.replace("_", "-"), dest="layers_" + f.name, default=None, type=typ,
                         metavar=typ.metavar,
                         help=_field_help(docs.get(f.name, ""), f) if documented else argparse.SUPPRESS)
