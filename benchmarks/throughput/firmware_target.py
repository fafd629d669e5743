"""Cost of the generated C observers (`pmsmjax export-c`) on Cortex-M targets, run under
QEMU: does the step fit the control period of a motor-control microcontroller?

For every observer the C export supports (`pmsmjax.firmware.supported_observers()`), on
its paper's motor with its default design, generated at T_s = 125 us, three builds with
Debian's `arm-none-eabi-gcc` (-O2, hard FPU, newlib's libm):

- Cortex-M4F, float32 (-mcpu=cortex-m4 -mfpu=fpv4-sp-d16 -mfloat-abi=hard);
- Cortex-M7, float32 and double (-mcpu=cortex-m7 -mfpu=fpv5-d16 -mfloat-abi=hard).

Per build:

- **sizes**: the observer's object (`arm-none-eabi-size`: text, data + bss), the code it
  links in with libm (a program calling `pmsm_obs_init` and `pmsm_obs_step`, minus the
  same program without them, both with --gc-sections), `sizeof(pmsm_obs_state)` (from
  the symbol table) and the stack frame of `pmsm_obs_step` (-fstack-usage; callees not
  included); the software double-precision routines (`__aeabi_d*`) the observer calls
  and those the program links in, with the libm member that needs them (a float32
  build calls none; on the single-precision FPU of the M4F it may link none);
- **instructions per step**, counted exactly: QEMU (`qemu-system-arm`, machine
  mps2-an386 / mps2-an500) runs the program one instruction per translation block
  (`-singlestep`; `one-insn-per-tb` from QEMU 8.1) and logs every block it executes
  (`-d exec,nochain`); the instructions from the entry of `pmsm_obs_step` to the return
  into the caller, libm included, over `--trace-steps` consecutive steps after the
  first sample (median and maximum);
- **cycles per step (M4F, estimated)** from the same trace and the instruction timings of
  the Cortex-M4 (its Technical Reference Manual): 1 cycle an instruction, 2 a single
  load or store, 1 + N a load or store of N registers, 3 a floating-point multiply-
  accumulate, 14 a VDIV/VSQRT, 12 an integer division, 2 more a taken branch; no wait
  states (code and data in zero-wait-state memory), no stalls: a lower estimate for a
  part running from flash without its cache;
- **the budget** at 170 MHz: 21,250 cycles at 8 kHz, 10,625 at 16 kHz; the largest
  estimated cycles of a step against them ("fits": both periods, 8 kHz only, or "does
  not fit");
- **accuracy on the target**: the program replays a closed-loop recording (0.2 s of the
  observer's paper drive in sensorless speed control, current noise; the samples
  compiled in) and prints every estimate as the hexadecimal bits of the number; the
  largest angle and speed deviation from `pmsmjax.replay` (float64, on the host) of the
  same recording, against the host float test's tolerance (1e-4 rad in float32, 1e-9 rad
  in double).

Install the toolchain with `benchmarks/install_arm_toolchain.sh` (Debian packages
gcc-arm-none-eabi, libnewlib-arm-none-eabi, qemu-system-arm). `tests/test_firmware.py`
uses the same build (`build`, `run`) for the Cortex-M4F.

Usage (from the repository root):

    python -m benchmarks.throughput.firmware_target [--observers eso,gi-leso] [--quick]
"""

from __future__ import annotations

import os
import re
import shutil
import statistics
import subprocess
import tempfile
from pathlib import Path

from .. import _harness as h


MODULE = "benchmarks.throughput.firmware_target"
T_S = 125e-6
CLOCK_HZ = 170e6
RATES_HZ = (8e3, 16e3)
TOOLS = ("arm-none-eabi-gcc", "arm-none-eabi-size", "arm-none-eabi-nm",
         "arm-none-eabi-objdump", "qemu-system-arm")

#: name: (gcc flags, QEMU machine); the builds: (target, float32)
TARGETS = {
    "cortex-m4f": (["-mcpu=cortex-m4", "-mthumb", "-mfpu=fpv4-sp-d16", "-mfloat-abi=hard"],
                   "mps2-an386"),
    "cortex-m7": (["-mcpu=cortex-m7", "-mthumb", "-mfpu=fpv5-d16", "-mfloat-abi=hard"],
                  "mps2-an500"),
}
BUILDS = (("cortex-m4f", True), ("cortex-m7", True), ("cortex-m7", False))
CFLAGS = ["-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-ffunction-sections",
          "-fdata-sections"]

# Vector table, FPU enable, .bss, semihosting (BKPT 0xAB: SYS_WRITE0, SYS_EXIT): the
# program runs from RAM in the emulator (the ELF's sections are loaded where they link).
STARTUP_C = r"""#include <stdint.h>
extern int main(void);
extern uint32_t __bss_start__, __bss_end__, __stack_top__;
void reset_handler(void);
static void halt(void) { for (;;) {} }
__attribute__((section(".vectors"), used))
const void *const vector_table[16] = {
    &__stack_top__, (const void *)reset_handler, (const void *)halt, (const void *)halt,
    (const void *)halt, (const void *)halt, (const void *)halt, 0, 0, 0, 0,
    (const void *)halt, (const void *)halt, 0, (const void *)halt, (const void *)halt};
static int semihost(int op, const void *arg)
{
    register int r0 __asm__("r0") = op;
    register const void *r1 __asm__("r1") = arg;
    __asm__ volatile("bkpt 0xab" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}
void target_write(const char *s) { semihost(0x04, s); }
void reset_handler(void)
{
    uint32_t *p;
    *(volatile uint32_t *)0xE000ED88 |= 0xFu << 20; /* CPACR: the FPU, full access */
    __asm__ volatile("dsb\n isb");
    for (p = &__bss_start__; p < &__bss_end__; p++) *p = 0;
    semihost(0x18, (const void *)(main() == 0 ? 0x20026 : 0x20024)); /* exit */
    halt();
}
"""

LINK_LD = """MEMORY { CODE (rx) : ORIGIN = 0x00000000, LENGTH = 4M
         DATA (rwx) : ORIGIN = 0x20000000, LENGTH = 4M }
ENTRY(reset_handler)
SECTIONS {
  .text : { KEEP(*(.vectors)) *(.text*) *(.rodata*) } > CODE
  .ARM.exidx : { *(.ARM.exidx*) } > CODE
  .data : { *(.data*) } > DATA
  .bss (NOLOAD) : { __bss_start__ = .; *(.bss*) *(COMMON) . = ALIGN(4);
                    __bss_end__ = .; } > DATA
  __stack_top__ = ORIGIN(DATA) + LENGTH(DATA);
}
"""

# the replay: every sample of recording.h, each estimate printed as the bits of the number
REPLAY_C = r"""#include "pmsm_observer.h"
#include "recording.h"
extern void target_write(const char *s);
pmsm_obs_state target_state;

static char *hex(char *p, const void *x, unsigned n)
{
    const unsigned char *b = (const unsigned char *)x;
    while (n--) {
        *p++ = "0123456789abcdef"[b[n] >> 4];
        *p++ = "0123456789abcdef"[b[n] & 15];
    }
    return p;
}

int main(void)
{
    pmsm_real u_prev[2] = {PMSM_R(0.0), PMSM_R(0.0)}, th, wh;
    char line[48], *p;
    int k;
    pmsm_obs_init(&target_state, REC_THETA0, REC_W0);
    for (k = 0; k < REC_N; k++) {
        pmsm_obs_step(&target_state, rec_i[k], u_prev, &th, &wh);
        p = hex(line, &th, sizeof th);
        *p++ = ',';
        p = hex(p, &wh, sizeof wh);
        *p++ = '\n';
        *p = 0;
        target_write(line);
        u_prev[0] = rec_u[k][0];
        u_prev[1] = rec_u[k][1];
    }
    return 0;
}
"""

# the footprint: the observer's calls with inputs the compiler cannot see (-DWITH_OBSERVER),
# or the same program without them
SIZE_C = r"""#include "pmsm_observer.h"
volatile pmsm_real size_in[4], size_out[2];
#ifdef WITH_OBSERVER
pmsm_obs_state size_state;
#endif
int main(void)
{
#ifdef WITH_OBSERVER
    pmsm_real i_ab[2], u_ab[2], th, wh;
    pmsm_obs_init(&size_state, size_in[0], size_in[1]);
    i_ab[0] = size_in[0]; i_ab[1] = size_in[1]; u_ab[0] = size_in[2]; u_ab[1] = size_in[3];
    pmsm_obs_step(&size_state, i_ab, u_ab, &th, &wh);
    size_out[0] = th;
    size_out[1] = wh;
#else
    size_out[0] = size_in[0];
#endif
    return 0;
}
"""


def missing_tools(tools=TOOLS) -> list[str]:
    """The tools of `tools` not on PATH (install: benchmarks/install_arm_toolchain.sh)."""
    return [t for t in tools if shutil.which(t) is None]


def _run(cmd, **kw):
    return subprocess.run([str(c) for c in cmd], check=True, capture_output=True,
                          text=True, **kw)


def recording_header(t, u_ab, i_ab, theta0: float, w0: float) -> str:
    """`recording.h`: the samples as constants of `pmsm_real` (the value the host's
    `replay_main` reads, rounded once to the number type)."""
    del t
    rows_i = ",\n".join(f"{{PMSM_R({float(a)!r}), PMSM_R({float(b)!r})}}" for a, b in i_ab)
    rows_u = ",\n".join(f"{{PMSM_R({float(a)!r}), PMSM_R({float(b)!r})}}" for a, b in u_ab)
    return (f"#define REC_N {len(i_ab)}\n#define REC_THETA0 PMSM_R({float(theta0)!r})\n"
            f"#define REC_W0 PMSM_R({float(w0)!r})\n"
            f"static const pmsm_real rec_i[REC_N][2] = {{\n{rows_i}}};\n"
            f"static const pmsm_real rec_u[REC_N][2] = {{\n{rows_u}}};\n")


def build(observer, T_s: float, out, target: str = "cortex-m4f", *, float32: bool = True,
          recording=None, sizes: bool = True) -> dict:
    """Generate `observer`'s C at `T_s` (s) into `out` and build it for `target`
    (`TARGETS`): the replay program of `recording` (`(t, u_ab, i_ab, theta0, w0)`,
    `replay.elf`) where given, and with `sizes` the footprint (`footprint`). Returns
    `{"elf": path or None, **sizes}`."""
    from pmsmjax.firmware import export_c

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    export_c(observer, T_s, out, float32=float32)
    (out / "startup.c").write_text(STARTUP_C)
    (out / "link.ld").write_text(LINK_LD)
    flags, _ = TARGETS[target]
    gcc = ["arm-none-eabi-gcc", *flags, *CFLAGS]
    _run([*gcc, "-fstack-usage", "-c", "-o", out / "pmsm_observer.o",
          out / "pmsm_observer.c"], cwd=out)
    _run([*gcc, "-c", "-o", out / "startup.o", out / "startup.c"])
    link = ["-nostartfiles", "-T", out / "link.ld", "-Wl,--gc-sections"]
    res = {"elf": None}
    if recording is not None:
        (out / "recording.h").write_text(recording_header(*recording))
        (out / "replay_main.c").write_text(REPLAY_C)
        res["elf"] = str(out / "replay.elf")
        _run([*gcc, *link, "-I", out, "-o", res["elf"], out / "replay_main.c",
              out / "pmsm_observer.o", out / "startup.o", "-lm"])
    if sizes:
        res.update(footprint(out, gcc, link))
    return res


def footprint(out: Path, gcc, link) -> dict:
    """Sizes of the build in `out` (bytes): `object_text`, `object_data` (data + bss of
    pmsm_observer.o), `linked_text` (what calling the observer adds to a program, libm
    included), `state`, `stack` (the frame of pmsm_obs_step); the software double
    routines (`__aeabi_d*`) the observer's object calls (`soft_double`), those linked in
    (`soft_double_linked`) and why (`soft_double_by`: the libm member and the symbol it
    needs from libgcc's double routines, from the link map)."""
    (out / "size_main.c").write_text(SIZE_C)
    elfs = {}
    for name, extra in (("with", ["-DWITH_OBSERVER"]), ("without", [])):
        elfs[name] = out / f"size_{name}.elf"
        _run([*gcc, *link, *extra, f"-Wl,-Map={elfs[name]}.map", "-I", out, "-o",
              elfs[name], out / "size_main.c", out / "pmsm_observer.o", out / "startup.o",
              "-lm"])

    def text(path):
        t, d, b = _run(["arm-none-eabi-size", path]).stdout.splitlines()[1].split()[:3]
        return int(t), int(d) + int(b)

    def soft(lines):
        return sorted({f[-1] for f in map(str.split, lines) if f and f[-1].startswith(
            "__aeabi_d")})

    obj_text, obj_data = text(out / "pmsm_observer.o")
    nm = _run(["arm-none-eabi-nm", "-S", elfs["with"]]).stdout.splitlines()
    # sizeof(pmsm_obs_state): the size of the symbol size_state
    state = next(int(f[1], 16) for f in map(str.split, nm) if f[-1] == "size_state")
    stack = None
    su = out / "pmsm_observer.su"
    if su.exists():
        for line in su.read_text().splitlines():
            if ":pmsm_obs_step\t" in line:
                stack = int(line.split("\t")[1])
    # "Archive member included to satisfy reference by file (symbol)": a libgcc double
    # routine's member, then the member that needed it and the symbol
    by = set()
    lines = Path(f"{elfs['with']}.map").read_text().split("Discarded input")[0].splitlines()
    for k, line in enumerate(lines[:-1]):
        if re.search(r"libgcc\.a\(_arm_\w*df\w*\.o\)", line):
            m = re.search(r"\((lib_a-)?([\w.]+)\.o\) \((\w+)\)", lines[k + 1])
            if m:
                by.add(f"{m.group(2)} ({m.group(3)})")
    return dict(object_text=obj_text, object_data=obj_data,
                linked_text=text(elfs["with"])[0] - text(elfs["without"])[0],
                state=state, stack=stack,
                soft_double=soft(_run(["arm-none-eabi-nm", "-u", out / "pmsm_observer.o"])
                                 .stdout.splitlines()),
                soft_double_linked=soft(nm), soft_double_by=sorted(by))


def _qemu(elf, target: str, extra=()):
    return ["qemu-system-arm", "-M", TARGETS[target][1], "-nographic", "-monitor", "none",
            "-serial", "none", "-semihosting-config", "enable=on,target=native", *extra,
            "-kernel", str(elf)]


def run(elf, target: str = "cortex-m4f", *, float32: bool = True, timeout: float = 120.0):
    """Run the replay program `elf` under QEMU: `(theta_hat, w_hat)` as float64 arrays
    (the target's numbers, read back from their bits)."""
    import numpy as np

    res = subprocess.run(_qemu(elf, target), capture_output=True, text=True,
                         timeout=timeout, check=True)
    dt = ">f4" if float32 else ">f8"
    rows = [ln.split(",") for ln in (res.stderr + res.stdout).splitlines()
            if re.fullmatch(r"[0-9a-f]+,[0-9a-f]+", ln)]
    a = np.array([[np.frombuffer(bytes.fromhex(x), dt)[0] for x in r] for r in rows],
                 dtype=np.float64).reshape(-1, 2)
    return a[:, 0], a[:, 1]


# ------------------------------------------------------------------ instructions, cycles

_LOAD_STORE = re.compile(r"^(ldr|str|vldr|vstr|ldrex|strex|pld|tbb|tbh)")
_MULTI = re.compile(r"^(ldm|stm|push|pop|vldm|vstm|vpush|vpop)")
_BRANCHES = {"b", "bl", "blx", "bx", "cbz", "cbnz"} | {
    "b" + c for c in "eq ne cs hs cc lo mi pl vs vc hi ls ge lt gt le".split()}
_MAC = re.compile(r"^(vmla|vmls|vnmla|vnmls|vfma|vfms|vfnma|vfnms)")


def _registers(operands: str) -> int:
    """The number of 32-bit registers in a register list such as `{r4, r5, lr}`,
    `{s16-s23}`, `{d8-d15}` (a d register is two)."""
    inner = operands[operands.find("{") + 1:operands.find("}")]
    n = 0
    for part in inner.split(","):
        part = part.strip()
        width = 2 if part.startswith("d") else 1
        if "-" in part:
            a, b = (int(re.sub(r"\D", "", x)) for x in part.split("-"))
            n += width * (b - a + 1)
        elif part:
            n += width
    return max(n, 1)


def instruction_table(elf) -> dict[int, tuple[int, int, bool]]:
    """`{address: (length in bytes, Cortex-M4 cycles if not a taken branch, is a
    branch)}` from the disassembly of `elf` (the timings of the module docstring)."""
    table = {}
    lines = _run(["arm-none-eabi-objdump", "-d", "--no-show-raw-insn", elf]).stdout
    rows = []
    for ln in lines.splitlines():
        m = re.match(r"\s*([0-9a-f]+):\s+(\S+)\s*(.*)", ln)
        if m:
            rows.append((int(m.group(1), 16), m.group(2).lower(), m.group(3)))
    for k, (addr, op, args) in enumerate(rows):
        size = rows[k + 1][0] - addr if k + 1 < len(rows) else 2
        base = op.split(".")[0]
        cyc = 1
        if base in ("vdiv", "vsqrt"):
            cyc = 14
        elif base in ("sdiv", "udiv"):
            cyc = 12
        elif _MULTI.match(base):
            cyc = 1 + _registers(args)
        elif _LOAD_STORE.match(base):
            cyc = 2
        elif _MAC.match(base):
            cyc = 3
        branch = (base in _BRANCHES or re.sub(r"[\s{}]", "", args).split(",")[0] == "pc"
                  or _MULTI.match(base) is not None and "pc" in args)
        table[addr] = (size if 0 < size <= 4 else 2, cyc, branch)
    return table


def count_instructions(elf, target: str, steps: int, timeout: float = 600.0) -> dict:
    """Instructions (and estimated Cortex-M4 cycles) of `steps` calls of `pmsm_obs_step`
    in the replay program `elf`, after the first: QEMU one instruction per block, every
    executed block logged (`-d exec,nochain`); a step runs from the entry of
    `pmsm_obs_step` to the first instruction back in `main`."""
    syms = {}
    for line in _run(["arm-none-eabi-nm", "-S", elf]).stdout.splitlines():
        f = line.split()
        if len(f) == 4 and f[2] in "Tt":
            syms[f[3]] = (int(f[0], 16) & ~1, int(f[1], 16))
    entry = syms["pmsm_obs_step"][0]
    main_lo, main_n = syms["main"]
    table = instruction_table(elf)
    insns, cycles = [], []
    with tempfile.TemporaryDirectory() as tmp:
        fifo = os.path.join(tmp, "trace")
        os.mkfifo(fifo)
        proc = subprocess.Popen(_qemu(elf, target, [*_one_insn_per_block(), "-d",
                                                    "exec,nochain", "-D", fifo]),
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            n = c = 0
            inside = False
            prev = None
            seen = 0
            with open(fifo) as f:
                for line in f:
                    if not line.startswith("Trace"):
                        continue
                    # [cs_base/pc/flags/cflags] symbol
                    pc = int(line[line.index("[") + 1:].split("/", 2)[1], 16)
                    if pc == entry and not inside:
                        inside, n, c, prev = True, 0, 0, None
                    elif inside and main_lo <= pc < main_lo + main_n:
                        inside = False
                        seen += 1
                        if seen > 1:  # the first sample takes another path
                            insns.append(n)
                            cycles.append(c + _taken(table, prev, pc))
                        if len(insns) >= steps:
                            break
                        continue
                    if inside:
                        n += 1
                        c += table.get(pc, (2, 1, False))[1] + _taken(table, prev, pc)
                        prev = pc
        finally:
            proc.kill()
            proc.wait(timeout=timeout)
    if not insns:
        raise RuntimeError(f"no step of pmsm_obs_step was traced in {elf}")
    return dict(insns_median=statistics.median(insns), insns_max=max(insns),
                cycles_median=statistics.median(cycles), cycles_max=max(cycles),
                steps=len(insns))


def _one_insn_per_block() -> list[str]:
    """QEMU's option for one guest instruction per translation block: `-singlestep`
    before QEMU 8.1, `-accel tcg,one-insn-per-tb=on` since."""
    out = _run(["qemu-system-arm", "--version"]).stdout
    m = re.search(r"version (\d+)\.(\d+)", out)
    if m and (int(m.group(1)), int(m.group(2))) >= (8, 1):
        return ["-accel", "tcg,one-insn-per-tb=on"]
    return ["-singlestep"]


def _taken(table, prev, pc) -> int:
    """2 cycles of pipeline refill where the branch at `prev` was taken (the next
    instruction is not the one after it)."""
    if prev is None:
        return 0
    size, _, branch = table.get(prev, (2, 1, False))
    return 2 if branch and pc != prev + size else 0


# ------------------------------------------------------------------------------ the run

def closed_loop_recording(drive, observer, t_end: float, T_s: float = T_S):
    """`(t, u_ab, i_ab, theta0, w0)` of `observer` in sensorless speed control of `drive`:
    0.2 p.u., a ramp to 0.6 p.u. from a quarter of the run, a 0.4 p.u. load step at
    three fifths, current noise 0.02 A (as tests/test_firmware.py's closed loop)."""
    import jax
    import numpy as np

    import pmsmjax as pj

    w_r, tau = float(drive.w_rated), float(drive.tau_rated)
    sc = pj.Scenario(t_end=t_end,
                     w_m_ref=pj.Profile([0.0, 0.25 * t_end, 0.5 * t_end, t_end],
                                        [0.2 * w_r, 0.2 * w_r, 0.6 * w_r, 0.6 * w_r]),
                     tau_L=pj.Profile([0.0, 0.6 * t_end, 0.62 * t_end, t_end],
                                      [0.0, 0.0, 0.4 * tau, 0.4 * tau]))
    tr = pj.simulate(drive, pj.FOC.from_drive(drive), observer, sc, T_s=T_s, theta0=0.3,
                     w_m0=0.2 * w_r, sensing=pj.Sensing(noise_std=0.02),
                     key=jax.random.PRNGKey(1))
    rec = pj.RecordedData.from_trajectory(tr)
    return (np.asarray(rec.t), np.asarray(rec.u_ab), np.asarray(rec.i_ab), 0.3, 0.2 * w_r)


def deviation(theta, w, theta_ref, w_ref) -> tuple[float, float]:
    """Largest angle (wrapped, rad) and speed (rad/s) deviation."""
    import numpy as np

    import pmsmjax as pj

    return (float(np.abs(np.asarray(pj.wrap_angle(theta - theta_ref))).max()),
            float(np.abs(w - w_ref).max()))


def budget_cycles(rate_hz: float) -> float:
    """Cycles of one control period at `rate_hz` on the CLOCK_HZ part."""
    return CLOCK_HZ / rate_hz


def measure(name: str, tmp, *, t_end: float, trace_steps: int, builds=BUILDS) -> list[dict]:
    """The rows of observer `name` (one per build)."""
    import numpy as np

    import pmsmjax as pj
    from pmsmjax.observers import make_observer

    drive = pj.preset(h.paper_drive(name))
    obs = make_observer(name, drive)
    rec = closed_loop_recording(drive, obs, t_end)
    t, u, i, theta0, w0 = rec
    th_ref, w_ref = (np.asarray(x) for x in pj.replay(obs, t=t, u_ab=u, i_ab=i, T_s=T_S,
                                                      theta0=theta0, w0=w0))
    rows = []
    for target, f32 in builds:
        prec = "float32" if f32 else "double"
        out = Path(tmp) / f"{name}-{target}-{prec}"
        b = build(obs, T_S, out, target, float32=f32, recording=rec)
        th, w = run(b["elf"], target, float32=f32)
        d_th, d_w = deviation(th, w, th_ref, w_ref)
        row = {"observer": name, "drive": drive.name, "target": target, "precision": prec,
               **{k: v for k, v in b.items() if k != "elf"},
               **count_instructions(b["elf"], target, trace_steps),
               "samples": len(th), "theta_dev_rad": d_th, "w_dev_rad_s": d_w,
               "theta_limit_rad": 1e-4 if f32 else 1e-9}
        row["within_limit"] = d_th <= row["theta_limit_rad"] and len(th) == len(t)
        if target == "cortex-m4f":
            for r in RATES_HZ:
                row[f"share_{int(r / 1e3)}khz"] = row["cycles_max"] / budget_cycles(r)
            row["fits"] = ("8 and 16 kHz" if row["share_16khz"] <= 1.0 else
                           "8 kHz only" if row["share_8khz"] <= 1.0 else "does not fit")
        rows.append(row)
        print(f"  {name} {target} {prec}: {row['insns_median']:.0f} instructions/step, "
              f"theta deviation {d_th:.2g} rad", flush=True)
    return rows


def _soft(row) -> str:
    """The software double routines of a build: the observer's own, else those libm
    links in and for what."""
    if row["soft_double"]:
        return "called: " + ", ".join(row["soft_double"])
    if row["soft_double_linked"]:
        return f"none called; libm links {len(row['soft_double_linked'])} in for " + \
            ", ".join(row["soft_double_by"])
    return "none"


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="the Cortex-M4F build only, 0.05 s "
                  "recordings, 8 traced steps")
    ap.add_argument("--observers", default=None,
                    help="comma-separated observers (default: every one the export supports)")
    h.size_option(ap, "--trace-steps", full=64, quick=8,
                  help="steps whose instructions are counted")
    args = h.parse_args(ap, argv)
    missing = missing_tools()
    if missing:
        raise SystemExit(f"missing: {', '.join(missing)}; install them with "
                         f"benchmarks/install_arm_toolchain.sh")
    from pmsmjax.firmware import supported_observers

    names = [n for n in h.observer_names(args.observers) if n in supported_observers()]
    steps = args.trace_steps
    builds = BUILDS[:1] if args.quick else BUILDS
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            rows += measure(name, tmp, t_end=0.05 if args.quick else 0.2,
                            trace_steps=steps, builds=builds)
    versions = {t: _run([t, "--version"]).stdout.splitlines()[0]
                for t in ("arm-none-eabi-gcc", "qemu-system-arm")}
    print(h.machine_line())
    print(f"{versions['arm-none-eabi-gcc']}; {versions['qemu-system-arm']}")
    m4 = [r for r in rows if r["target"] == "cortex-m4f"]
    h.table(m4, [("observer", "observer", ""), ("code (B)", "object_text", "d"),
                 ("with libm (B)", "linked_text", "d"), ("state (B)", "state", "d"),
                 ("stack (B)", "stack", "d"),
                 ("instructions/step", lambda r: f"{r['insns_median']:.0f} "
                  f"(max {r['insns_max']})", ""),
                 ("cycles (est.)", "cycles_max", ".0f"),
                 ("8 kHz", lambda r: f"{100 * r['share_8khz']:.1f} %", ""),
                 ("16 kHz", lambda r: f"{100 * r['share_16khz']:.1f} %", ""),
                 ("fits", "fits", ""),
                 ("soft double", _soft, ""),
                 ("angle vs replay (rad)", "theta_dev_rad", ".2g")],
            title=f"Cortex-M4F, float32 (budget at {CLOCK_HZ / 1e6:.0f} MHz: "
                  f"{budget_cycles(8e3):,.0f} cycles at 8 kHz, "
                  f"{budget_cycles(16e3):,.0f} at 16 kHz)")
    m7 = [r for r in rows if r["target"] == "cortex-m7"]
    if m7:
        h.table(m7, [("observer", "observer", ""), ("precision", "precision", ""),
                     ("code (B)", "object_text", "d"), ("with libm (B)", "linked_text", "d"),
                     ("state (B)", "state", "d"),
                     ("instructions/step", lambda r: f"{r['insns_median']:.0f} "
                      f"(max {r['insns_max']})", ""),
                     ("soft double", _soft, ""),
                     ("angle vs replay (rad)", "theta_dev_rad", ".2g")],
                title="Cortex-M7 (fpv5-d16)")
    # a float32 build calls no software double routine, and on the single-precision FPU
    # links none in
    bad = [f"{r['observer']} {r['target']} {r['precision']}" for r in rows
           if not r["within_limit"] or r["precision"] == "float32" and (
               r["soft_double"] or r["target"] == "cortex-m4f" and r["soft_double_linked"])]
    h.write_report(args.json, rows, benchmark=MODULE, T_s=T_S, clock_hz=CLOCK_HZ,
                   trace_steps=steps, **versions)
    if bad:
        print(f"outside the limits (or software double in float32): {', '.join(bad)}")
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
