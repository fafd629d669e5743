"""The command-line reference (Markdown), written from the argparse parsers themselves.

`reference_markdown()` lists every command of `pmsmjax` (and `python -m tuning`, whose
two commands `pmsmjax tune`/`pmsmjax compare` run), with its description, usage and
one table per option group: option, value (the metavar: its unit or form), help with
the default. The documentation site's hook (`docs/_hooks.py`) puts it into the page
`docs/cli.md` at build time, so the reference cannot drift from the parsers.
`python -m pmsmjax.cli._reference` prints it. `tune` and `compare` import the `tuning`
package (only when this function runs).
"""

from __future__ import annotations

import argparse


#: Where the generated reference goes in docs/cli.md.
MARKER = "<!-- cli-reference -->"


def _parsers() -> dict[str, argparse.ArgumentParser]:
    from .__main__ import build_parser
    from ._tuning import tuning_module

    root = build_parser()
    sub = next(a for a in root._actions if isinstance(a, argparse._SubParsersAction))
    out = {}
    for name, parser in sub.choices.items():
        if name in ("tune", "compare"):
            parser = tuning_module(name).build_parser(prog=f"pmsmjax {name}")
        out[name] = parser
    return out


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _value(action: argparse.Action) -> str:
    if action.nargs == 0:
        return ""
    meta = action.metavar
    if meta is None and action.choices is not None:
        meta = "{" + ",".join(map(str, action.choices)) + "}"
    if meta is None:
        meta = action.dest.upper()
    if isinstance(meta, tuple):
        meta = " ".join(meta)
    if action.nargs in ("+", "*"):
        meta = f"{meta} [{meta} ...]"
    return f"`{meta}`"


def _help(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    if not action.help:
        return ""
    text = parser._get_formatter()._expand_help(action)
    for empty in (" (default: None)", " (default: False)", " (default: [])"):
        text = text.replace(empty, "")  # added by ArgumentDefaultsHelpFormatter
    default = action.default
    if ("%(default)" not in action.help and default not in (None, False, [], ())
            and default is not argparse.SUPPRESS and action.nargs != 0
            and "default" not in text):
        text += f" (default: {default})"
    return _cell(text)


def _command(name: str, parser: argparse.ArgumentParser) -> list[str]:
    lines = [f"## `pmsmjax {name}`", ""]
    if parser.description:
        lines += [" ".join(parser.description.split()), ""]
    usage = parser.format_usage().strip()
    usage = usage[len("usage: "):] if usage.startswith("usage: ") else usage
    lines += ["```text", usage, "```", ""]
    for group in parser._action_groups:
        rows = [f"| {', '.join(f'`{o}`' for o in action.option_strings)} | "
                f"{_value(action)} | {_help(parser, action)} |"
                for action in group._group_actions
                if action.option_strings and not isinstance(action, argparse._HelpAction)]
        if rows:
            title = group.title if group.title not in ("options", "optional arguments") \
                else "options"
            lines += [f"**{title}**", "", "| option | value | meaning |", "|---|---|---|",
                      *rows, ""]
    if parser.epilog:
        lines += [" ".join(parser.epilog.split()), ""]
    return lines


def reference_markdown() -> str:
    """The reference of every command, as Markdown (one `##` section per command)."""
    parsers = _parsers()
    lines = ["Commands: " + ", ".join(f"[`{n}`](#pmsmjax-{n})" for n in parsers) + ".", ""]
    for name, parser in parsers.items():
        lines += _command(name, parser)
    return "\n".join(lines)


if __name__ == "__main__":
    print(reference_markdown())
