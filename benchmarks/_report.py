"""The JSON file a benchmark writes: its rows and the machine that measured them."""

from __future__ import annotations

import datetime
import json
import os
import platform
from pathlib import Path


def write_report(out, rows, **extra) -> Path:
    """Write `{"meta": ..., "rows": rows}` to `out` (folders created) and say where: the
    meta block holds the date (UTC), the machine, processor, CPU count, Python and JAX
    versions, and `extra` (e.g. load averages, time limits)."""
    import jax

    meta = dict(date=datetime.datetime.now(datetime.timezone.utc).isoformat(),
                machine=platform.machine(), processor=platform.processor(),
                cpus=os.cpu_count(), python=platform.python_version(), jax=jax.__version__,
                **extra)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(dict(meta=meta, rows=rows), indent=2))
    print(f"wrote {out}")
    return out
