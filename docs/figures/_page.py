"""What the docs/figures scripts share: a Markdown table, and writing a block of text
between a page's markers."""

import re


def markdown_table(columns: list[tuple[str, str]], rows: list[list[str]]) -> str:
    """The Markdown table of `rows` (each a list of cell texts) under `columns`, each a
    `(heading, align)` with align "l" or "r"."""
    head = "| " + " | ".join(h for h, _ in columns) + " |"
    rule = "|" + "|".join("---:" if a == "r" else "---" for _, a in columns) + "|"
    return "\n".join([head, rule, *("| " + " | ".join(r) + " |" for r in rows)])


def write_block(page: str, begin: str, end: str, text: str) -> None:
    """Replace what lies between the markers `begin` and `end` of the file `page` with
    `text`; `SystemExit` naming the page when it has no such block."""
    with open(page) as f:
        old = f.read()
    new, n = re.subn(re.escape(begin) + ".*?" + re.escape(end),
                     lambda _: f"{begin}\n{text}\n{end}", old, flags=re.S)
    if n != 1:
        raise SystemExit(f"{page}: no {begin} ... {end} block to write the table into")
    with open(page, "w") as f:
        f.write(new)
