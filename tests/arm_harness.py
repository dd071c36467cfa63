"""Cross-compile generated firmware for Cortex-M4F and Cortex-M0+ and run it under QEMU.

Used by ``tests/test_codegen_arm.py`` and ``benchmarks/bench_codegen.py``. Needs Debian's
``gcc-arm-none-eabi`` (with ``libnewlib-arm-none-eabi`` for its headers) and ``qemu-system-arm``;
:func:`toolchain` says which tool is missing.

The program is bare metal: a vector table and reset handler (``STARTUP``), semihosting calls for
file I/O and the exit status (``SEMIHOSTING``, ``bkpt 0xAB``), and a driver (``DRIVER``) that
reads samples from ``in.bin`` in chunks, calls ``<prefix>_update`` and ``<prefix>_read`` for each
and writes the reading (revolutions, angle bits, flags) to ``out.bin``; with the power-up
decoder (``<PREFIX>_POWERUP``) the flags word also carries ``pole_pair << 16`` and
``identified << 31``, as in the host driver of ``tests/firmware_support.py``. The generated
sources are compiled alone into an object first (strict warnings, ``-Werror``), so that
``nm -u`` and ``size`` see the generated code only.

Machines: ``mps2-an386`` (Cortex-M4 with FPU) for the float variant, ``microbit`` (nRF51,
Cortex-M0; the same ARMv6-M instruction set as the M0+ the code is compiled for) for the fixed
variant. Instruction traces come from QEMU's ``-singlestep -d exec,nochain`` restricted with
``-dfilter`` to the generated functions; cycles are estimated from them with the Cortex-M4
timing table :data:`M4_CYCLES` (Cortex-M4 TRM r0p1, tables 3-1 and 7-1).
"""

from __future__ import annotations

import re
import shutil
import subprocess
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

TOOLS = (
    "arm-none-eabi-gcc",
    "arm-none-eabi-nm",
    "arm-none-eabi-size",
    "arm-none-eabi-objdump",
    "qemu-system-arm",
)
CHUNK = 64  # samples per semihosting read (microbit: 16 kB of RAM)
STRICT = (
    "-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Wconversion", "-Wshadow",
    "-Wdouble-promotion", "-Wfloat-equal", "-Wcast-qual", "-Wundef", "-Werror",
)  # fmt: skip


@dataclass(frozen=True)
class Target:
    """A CPU, its compiler flags and the QEMU machine that runs it."""

    name: str
    cflags: tuple[str, ...]
    machine: str
    flash: str
    ram: str


TARGETS = {
    "m4f": Target(
        "Cortex-M4F",
        ("-mcpu=cortex-m4", "-mthumb", "-mfpu=fpv4-sp-d16", "-mfloat-abi=hard"),
        "mps2-an386",
        "4M",
        "4M",
    ),
    "m0plus": Target(
        "Cortex-M0+",
        ("-mcpu=cortex-m0plus", "-mthumb", "-mfloat-abi=soft"),
        "microbit",
        "256K",
        "16K",
    ),
}

LINKER = """\
MEMORY {{ FLASH (rx) : ORIGIN = 0x00000000, LENGTH = {flash}
         RAM (rwx) : ORIGIN = 0x20000000, LENGTH = {ram} }}
SECTIONS {{
  .text : {{ KEEP(*(.vectors)) *(.text*) *(.rodata*) }} > FLASH
  .data : {{ __data_start = .; *(.data*) . = ALIGN(4); __data_end = .; }} > RAM AT > FLASH
  __data_load = LOADADDR(.data);
  .bss (NOLOAD) : {{ __bss_start = .; *(.bss*) *(COMMON) . = ALIGN(4); __bss_end = .; }} > RAM
  __stack_top = ORIGIN(RAM) + LENGTH(RAM);
}}
"""

STARTUP = r"""
#include <stdint.h>
extern uint32_t __data_load, __data_start, __data_end, __bss_start, __bss_end, __stack_top;
int main(void);
void hc_exit(int code);
void Reset_Handler(void);
void Default_Handler(void);
void Reset_Handler(void)
{
    uint32_t *src = &__data_load;
    uint32_t *dst = &__data_start;
    while (dst < &__data_end) {
        *dst++ = *src++;
    }
    for (dst = &__bss_start; dst < &__bss_end; ++dst) {
        *dst = 0u;
    }
#if defined(__ARM_FP)
    *(volatile uint32_t *)0xE000ED88u |= (0xFu << 20); /* CPACR: enable CP10/CP11 (the FPU) */
    __asm__ volatile("dsb\n isb" ::: "memory");
#endif
    hc_exit(main());
}
void Default_Handler(void) { hc_exit(99); }
__attribute__((section(".vectors"), used)) static const void *const vectors[16] = {
    &__stack_top, (const void *)Reset_Handler, (const void *)Default_Handler,
    (const void *)Default_Handler, (const void *)Default_Handler, (const void *)Default_Handler,
    (const void *)Default_Handler, 0, 0, 0, 0, (const void *)Default_Handler,
    (const void *)Default_Handler, 0, (const void *)Default_Handler, (const void *)Default_Handler,
};
"""

SEMIHOSTING = r"""
#include <stdint.h>
static int semi(int op, void *arg)
{
    register int r0 __asm__("r0") = op;
    register void *r1 __asm__("r1") = arg;
    __asm__ volatile("bkpt 0xAB" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}
int hc_open(const char *name, int mode)
{
    int len = 0;
    while (name[len] != 0) {
        ++len;
    }
    uint32_t a[3] = {(uint32_t)name, (uint32_t)mode, (uint32_t)len};
    return semi(0x01, a);
}
int hc_read(int fd, void *buf, int n)
{
    uint32_t a[3] = {(uint32_t)fd, (uint32_t)buf, (uint32_t)n};
    return n - semi(0x06, a);
}
int hc_write(int fd, const void *buf, int n)
{
    uint32_t a[3] = {(uint32_t)fd, (uint32_t)buf, (uint32_t)n};
    return n - semi(0x05, a);
}
void hc_close(int fd)
{
    uint32_t a[1] = {(uint32_t)fd};
    (void)semi(0x02, a);
}
void hc_exit(int code)
{
    uint32_t a[2] = {0x20026u, (uint32_t)code}; /* ADP_Stopped_ApplicationExit, status */
    (void)semi(0x20, a);
    for (;;) {
    }
}
"""

DRIVER = r"""
#include <stdint.h>
#include "PFX_HEADER"
int hc_open(const char *name, int mode);
int hc_read(int fd, void *buf, int n);
int hc_write(int fd, const void *buf, int n);
void hc_close(int fd);
#define CHUNK_N CHUNK_VALUE
#if HC_Q
typedef int32_t in_t;
static PFX_q_state st;
#else
typedef float in_t;
static PFX_state st;
#endif
static in_t in[3 * CHUNK_N];
static uint32_t out[3 * CHUNK_N];
static void init(void)
{
#if HC_Q
    PFX_q_init(&st);
#else
    PFX_init(&st); /* one signature for every variant */
#endif
}
int main(void)
{
    const int fi = hc_open("in.bin", 1);
    const int fo = hc_open("out.bin", 5);
    const int fb = hc_open("block.bin", 1); /* optional: re-init every this many samples */
    uint32_t block = 0u;
    uint32_t count = 0u;
    int got;
    int k;
    if ((fi < 0) || (fo < 0)) {
        return 2;
    }
    if (fb >= 0) {
        (void)hc_read(fb, &block, (int)sizeof block);
        hc_close(fb);
    }
    init();
    for (;;) {
        got = hc_read(fi, in, (int)sizeof in) / (int)(3 * sizeof(in_t));
        if (got <= 0) {
            break;
        }
        for (k = 0; k < got; ++k) {
            if ((block != 0u) && (count != 0u) && ((count % block) == 0u)) {
                init();
            }
            count = count + 1u;
#if HC_Q
            PFX_q_reading r;
            (void)PFX_q_update(&st, in[3 * k], in[3 * k + 1], in[3 * k + 2]);
            PFX_q_read(&st, &r);
            out[3 * k] = (uint32_t)r.revolutions;
            out[3 * k + 1] = r.angle;
#else
            PFX_reading r;
            union { float f; uint32_t u; } bits;
            (void)PFX_update(&st, in[3 * k], in[3 * k + 1], in[3 * k + 2]);
            PFX_read(&st, &r);
            bits.f = r.angle;
            out[3 * k] = (uint32_t)r.revolutions;
            out[3 * k + 1] = bits.u;
#endif
            out[3 * k + 2] = r.flags;
#if !HC_Q && defined(UPFX_POWERUP)
            out[3 * k + 2] |= (r.pole_pair << 16) | (r.identified << 31);
#endif
        }
        const int bytes = got * (int)(3 * sizeof(uint32_t));
        if (hc_write(fo, out, bytes) != bytes) {
            return 3;
        }
    }
    hc_close(fi);
    hc_close(fo);
    return 0;
}
"""

#: Cortex-M4 cycles per instruction (TRM r0p1, table 3-1 and the FPU table 7-1), by mnemonic
#: without condition code, width suffix or the ``s`` flag suffix; everything from zero-wait-state
#: memory. Applied in :func:`trace` with the TRM's load/store notes: ``STR Rx,[Ry,#imm]`` is one
#: cycle; an integer load or store right after an integer load (whose result is not the next
#: address's base) is one cycle less. Floating-point loads and stores (VLDR, VSTR) are counted as
#: 2 always; taken branches as 1 + P with P = 2 (pipeline refill, the TRM gives 1..3);
#: multi-register transfers as 1 + N (+ P when they load the PC).
M4_CYCLES: dict[str, int] = {
    **dict.fromkeys(
        "add adc sub sbc rsb neg addw subw mov mvn cmp cmn and orr orn eor bic tst teq lsl lsr "
        "asr ror rrx "
        "uxth uxtb sxth sxtb ubfx sbfx bfi bfc clz rbit rev rev16 revsh movw movt adr nop "
        "usat ssat mul".split(),
        1,
    ),
    **dict.fromkeys("mla mls".split(), 2),
    **dict.fromkeys("umull smull umlal smlal".split(), 1),
    **dict.fromkeys("sdiv udiv".split(), 12),
    **dict.fromkeys("ldr ldrh ldrb ldrsh ldrsb str strh strb".split(), 2),
    **dict.fromkeys("ldrd strd".split(), 3),
    "it": 1,
    **dict.fromkeys("vadd vsub vmul vnmul vabs vneg vcmp vcmpe vcvt vmov vmrs vmsr".split(), 1),
    **dict.fromkeys("vmla vmls vnmla vnmls vfma vfms vfnma vfnms".split(), 3),
    **dict.fromkeys("vdiv vsqrt".split(), 14),
    **dict.fromkeys("vldr vstr".split(), 2),
}
_BRANCHES = ("b", "bl", "bx", "blx", "cbz", "cbnz")
_MULTI = ("push", "pop", "ldm", "stm", "ldmia", "stmia", "ldmdb", "stmdb", "vpush", "vpop",
          "vldm", "vstm", "vldmia", "vstmia")  # fmt: skip
_INT_LOADS = ("ldr", "ldrh", "ldrb", "ldrsh", "ldrsb")
_INT_STORES = ("str", "strh", "strb")
_CONDS = ("eq ne cs cc mi pl vs vc hi ls ge lt gt le al hs lo").split()


def toolchain() -> str | None:
    """None when every tool is on PATH, else the name of the first missing one."""
    for tool in TOOLS:
        if shutil.which(tool) is None:
            return tool
    return None


def _run(cmd: list[str], cwd: Path | None = None, timeout: float = 120.0) -> str:
    res = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout)
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({res.returncode}):\n{res.stdout}{res.stderr}")
    return res.stdout


@dataclass
class Build:
    """A cross-compiled program and the object of the generated code."""

    target: Target
    elf: Path
    obj: Path
    workdir: Path
    fixed: bool
    prefix: str
    functions: dict[str, tuple[int, int]] = field(default_factory=dict)  # name -> (addr, size)


def build(
    gen_dir: Path, workdir: Path, *, target: str, fixed: bool, prefix: str = "hallcal",
    opt: str = "-O2",
) -> Build:  # fmt: skip
    """Compile the generated variant (strict, alone) and link it with the driver."""
    t = TARGETS[target]
    workdir.mkdir(parents=True, exist_ok=True)
    gcc = "arm-none-eabi-gcc"
    stem = f"{prefix}_q" if fixed else prefix
    obj = workdir / f"{stem}_{target}.o"
    _run([gcc, *t.cflags, *STRICT, opt, "-ffunction-sections", "-c", str(gen_dir / f"{stem}.c"),
          "-o", str(obj)])  # fmt: skip
    (workdir / "startup.c").write_text(STARTUP)
    (workdir / "semihosting.c").write_text(SEMIHOSTING)
    drv = (
        DRIVER.replace("PFX_HEADER", f"{stem}.h")
        .replace("UPFX", prefix.upper())
        .replace("PFX", prefix)
    )
    (workdir / "driver.c").write_text(drv.replace("CHUNK_VALUE", str(CHUNK)))
    ld = workdir / f"link_{target}.ld"
    ld.write_text(LINKER.format(flash=t.flash, ram=t.ram))
    elf = workdir / f"{stem}_{target}.elf"
    _run([gcc, *t.cflags, "-std=gnu99", "-O2", "-ffreestanding", "-nostdlib",
          f"-DHC_Q={int(fixed)}",
          f"-I{gen_dir}", "-T", str(ld), str(workdir / "startup.c"),
          str(workdir / "semihosting.c"), str(workdir / "driver.c"), str(obj), "-lgcc",
          "-o", str(elf)])  # fmt: skip
    b = Build(t, elf, obj, workdir, fixed, prefix)
    own = set(_symbols(obj))
    for name, (addr, size, kind) in _symbols(elf).items():
        if name in own and kind in "tT" and size > 0:
            b.functions[name] = (addr & ~1, size)
    return b


def _symbols(path: Path) -> dict[str, tuple[int, int, str]]:
    out = {}
    text = _run(["arm-none-eabi-nm", "-S", "--defined-only", str(path)])
    for line in text.splitlines():
        parts = line.split()
        if len(parts) == 4:
            out[parts[3]] = (int(parts[0], 16), int(parts[1], 16), parts[2])
    return out


def undefined_symbols(obj: Path) -> list[str]:
    """``arm-none-eabi-nm -u``: what the object needs from libraries (libm, libgcc, ...)."""
    return [line.split()[-1] for line in _run(["arm-none-eabi-nm", "-u", str(obj)]).splitlines()
            if line.strip()]  # fmt: skip


def sizes(obj: Path) -> dict[str, int]:
    """``arm-none-eabi-size`` of the object: text, data, bss."""
    lines = _run(["arm-none-eabi-size", str(obj)]).splitlines()
    text, data, bss = (int(v) for v in lines[1].split()[:3])
    return {"text": text, "data": data, "bss": bss}


def function_sizes(b: Build) -> dict[str, int]:
    """Bytes of code per function of the generated object."""
    return {name: size for name, (_, size) in b.functions.items()}


def _qemu(b: Build, extra: list[str], timeout: float) -> None:
    cmd = ["qemu-system-arm", "-M", b.target.machine, "-nographic", "-monitor", "none",
           "-serial", "none", "-semihosting-config", "enable=on,target=native",
           *extra, "-kernel", str(b.elf)]  # fmt: skip
    res = subprocess.run(cmd, cwd=b.workdir, capture_output=True, text=True, timeout=timeout)
    if res.returncode != 0:
        raise RuntimeError(f"QEMU exit status {res.returncode}: {res.stdout}{res.stderr}")


def run(b: Build, samples: np.ndarray, *, block: int = 0, timeout: float = 120.0) -> np.ndarray:
    """Run the program on samples (N x 3; float32 or int32 as the variant takes); with
    ``block`` > 0 the state is re-initialised every ``block`` samples.

    Returns
    -------
    ndarray, shape (N, 3), uint32
        Revolutions (two's complement), angle bits (float32 bits or Q0.32 turns), flags.
    """
    data = np.ascontiguousarray(samples, dtype=np.int32 if b.fixed else np.float32)
    (b.workdir / "in.bin").write_bytes(data.tobytes())
    (b.workdir / "block.bin").write_bytes(np.uint32(block).tobytes())
    out = b.workdir / "out.bin"
    out.unlink(missing_ok=True)
    _qemu(b, [], timeout)
    return np.frombuffer(out.read_bytes(), dtype=np.uint32).reshape(-1, 3)


def angles(b: Build, raw: np.ndarray) -> np.ndarray:
    """y_star [rad] from :func:`run`'s output."""
    rev = raw[:, 0].view(np.int32).astype(np.float64)
    if b.fixed:
        return 2.0 * np.pi * (rev + raw[:, 1].astype(np.float64) / 2.0**32)
    return 2.0 * np.pi * rev + raw[:, 1].copy().view(np.float32).astype(np.float64)


@dataclass(frozen=True)
class Trace:
    """Instructions executed in the generated code, per call of ``<prefix>_update``."""

    counts: np.ndarray  # instructions per sample
    cycles: np.ndarray  # Cortex-M4 cycle estimate per sample
    mnemonics: Counter  # over all samples
    unknown: Counter  # mnemonics without a timing (counted as 1 cycle)
    per_pc: dict = field(default_factory=dict)  # pc -> [executions, cycles, mnemonic, operands]


def _disassembly(b: Build) -> dict[int, tuple[str, str, int]]:
    """pc -> (mnemonic, operands, size in bytes) for the generated functions."""
    text = _run(["arm-none-eabi-objdump", "-d", "--no-show-raw-insn", str(b.elf)])
    out: dict[int, tuple[str, str, int]] = {}
    lo = min(a for a, _ in b.functions.values())
    hi = max(a + s for a, s in b.functions.values())
    line_re = re.compile(r"^\s*([0-9a-f]+):\s+(\S+)\s*([^;<@]*)")
    pcs = []
    for line in text.splitlines():
        m = line_re.match(line)
        if m:
            pc = int(m.group(1), 16)
            if lo <= pc < hi:
                pcs.append((pc, m.group(2), m.group(3).strip()))
    for (pc, mn, ops), nxt in zip(pcs, [p for p, _, _ in pcs[1:]] + [hi], strict=True):
        out[pc] = (mn, ops, nxt - pc)
    return out


def _base(mnemonic: str) -> str:
    mn = mnemonic.lower().split(".")[0]
    if mn.startswith("v"):
        return mn
    if mn in _BRANCHES or mn in _MULTI or mn in M4_CYCLES:
        return mn
    for c in _CONDS:  # conditional forms: addeq, bne, ...
        if mn.endswith(c) and (mn[: -len(c)] in M4_CYCLES or mn[: -len(c)] in _BRANCHES):
            return mn[: -len(c)]
    if mn.endswith("s") and mn[:-1] in M4_CYCLES:
        return mn[:-1]
    for c in _CONDS:
        if mn.endswith("s" + c) and mn[: -len(c) - 1] in M4_CYCLES:
            return mn[: -len(c) - 1]
    if mn.startswith("it"):
        return "it"
    return mn


def _fp_base(mn: str) -> str:
    for c in _CONDS:
        if mn.endswith(c) and mn[: -len(c)] in M4_CYCLES:
            return mn[: -len(c)]
    return mn


def _register_count(ops: str) -> int:
    """Registers in a list such as ``{r4, r5, r6, lr}`` or ``{s16-s19}``."""
    inner = ops[ops.find("{") + 1 : ops.find("}")] if "{" in ops else ops
    count = 0
    for part in inner.split(","):
        part = part.strip()
        if "-" in part:
            a, z = part.split("-")
            count += int(re.sub(r"\D", "", z)) - int(re.sub(r"\D", "", a)) + 1
        elif part:
            count += 1
    return max(count, 1)


def _traced_pcs(b: Build, ranges: dict, samples: np.ndarray, block: int, timeout: float
                ) -> list[int]:  # fmt: skip
    """The program counters QEMU executes inside ``ranges`` (name -> (address, size)) while the
    harness feeds ``samples`` (re-initialising every ``block`` samples), in order."""
    data = np.ascontiguousarray(samples, dtype=np.int32 if b.fixed else np.float32)
    (b.workdir / "in.bin").write_bytes(data.tobytes())
    (b.workdir / "block.bin").write_bytes(np.uint32(block).tobytes())
    log = b.workdir / "trace.log"
    log.unlink(missing_ok=True)
    dfilter = ",".join(f"0x{a:x}+0x{s:x}" for a, s in ranges.values())
    _qemu(b, ["-singlestep", "-d", "exec,nochain", "-dfilter", dfilter, "-D", str(log)], timeout)
    pcs = [int(h, 16) for h in re.findall(r"/([0-9a-f]{8})/[0-9a-f]{8}/[0-9a-f]{8}\]",
                                          log.read_text())]  # fmt: skip
    log.unlink(missing_ok=True)
    return pcs


#: Kinds of instruction for :func:`trace`'s cycle estimate (:func:`_decode`).
_BRANCH, _LOAD_STORE, _FIXED, _UNKNOWN = range(4)


def _decode(instruction: tuple[str, str, int]) -> tuple:
    """What :func:`trace` needs of one instruction ``(mnemonic, operands, size)``, once per
    address: ``(base, kind, cycles, base register, destination of an integer load or None,
    size, mnemonic, operands)``. The cycles are those of the instruction alone: a branch's
    depend on whether it was taken, and a load or store not of the always-one-cycle form
    ``STR Rx, [Ry, #imm]`` costs 1 instead of 2 when pipelined with the previous load: the
    trace decides those."""
    mn, ops, size = instruction
    base = _fp_base(mn.lower().split(".")[0]) if mn.startswith("v") else _base(mn)
    load_dest = ops.split(",")[0].strip() if base in _INT_LOADS else None
    base_reg = ""
    if base in _BRANCHES:
        kind, cost = _BRANCH, 1
    elif base in _MULTI:
        kind, cost = _FIXED, 1 + _register_count(ops) + (2 if "pc" in ops else 0)
    elif base in _INT_LOADS or base in _INT_STORES:
        kind, cost = _LOAD_STORE, 2
        base_reg = ops.split("[", 1)[1].split(",")[0].split("]")[0].strip() if "[" in ops else ""
        if base in _INT_STORES and re.search(r"\[\w+(, #-?\d+)?\]$", ops.strip()):
            kind, cost = _FIXED, 1  # STR Rx, [Ry, #imm] is always one cycle
    elif base in M4_CYCLES:
        kind, cost = _FIXED, M4_CYCLES[base]
    else:
        kind, cost = _UNKNOWN, 1
    return base, kind, cost, base_reg, load_dest, size, mn, ops


def trace(b: Build, samples: np.ndarray, *, entry: str | None = None,
          timeout: float = 300.0, block: int = 0) -> Trace:  # fmt: skip
    """Count the instructions of each ``update`` call (QEMU single-step trace).

    Every function of the generated object except the reader, init and clear-fault ones is
    traced (static helpers the compiler did not inline, and the power-up decoder's
    ``_identify_sample``, are counted with the update they serve). With ``block`` > 0 the state
    is re-initialised every ``block`` samples (as :func:`run`).
    """
    entry = entry or (f"{b.prefix}_q_update" if b.fixed else f"{b.prefix}_update")
    skip = ("_read", "_init", "_clear_fault")
    ranges = {k: v for k, v in b.functions.items() if not k.endswith(skip)}
    start = ranges[entry][0]
    pcs = _traced_pcs(b, ranges, samples, block, timeout)
    dis = _disassembly(b)
    counts, cycles = [], []
    mnem: Counter = Counter()
    unknown: Counter = Counter()
    per_pc: dict[int, list] = {}
    decoded: dict[int, tuple] = {}  # pc -> what does not depend on the run (_decode)
    prev_load: str | None = None  # destination register of the previous integer load
    n = c = 0
    started = False
    for k, pc in enumerate(pcs):
        if pc == start:
            if started:
                counts.append(n)
                cycles.append(c)
            started, n, c = True, 0, 0
        if not started:
            continue
        d = decoded.get(pc)
        if d is None:
            d = decoded[pc] = _decode(dis.get(pc, ("?", "", 2)))
        base, kind, cost, base_reg, load_dest = d[0], d[1], d[2], d[3], d[4]
        n += 1
        mnem[base] += 1
        if kind == _BRANCH:
            nxt = pcs[k + 1] if k + 1 < len(pcs) else None
            cost = 3 if nxt is not None and nxt != pc + d[5] else 1  # taken: 3
        elif kind == _LOAD_STORE:
            if prev_load is not None and base_reg != prev_load and base_reg != "pc":
                cost = 1  # pipelined with the previous load
        elif kind == _UNKNOWN:
            unknown[base] += 1
        c += cost
        prev_load = load_dest
        rec = per_pc.get(pc)
        if rec is None:
            rec = per_pc[pc] = [0, 0, d[6], d[7]]
        rec[0] += 1
        rec[1] += cost
    if started:
        counts.append(n)
        cycles.append(c)
    return Trace(np.array(counts), np.array(cycles), mnem, unknown, per_pc)


# ------------------------------------------------------------------------------------------
# Cycle models for the worst case: branch penalty, flash wait states, the Cortex-M0+
# ------------------------------------------------------------------------------------------

#: Cortex-M0+ cycles per instruction (Cortex-M0+ TRM r0p1, table 3-1 "Cortex-M0+ instruction
#: summary"): ALU 1, loads and stores 2, taken branch 2 (B, Bcc, BX, BLX) and 3 (BL),
#: not-taken Bcc 1, PUSH/POP/LDM/STM 1 + N (POP with the PC 3 + N), MULS 1 or 32 (the
#: implementer's multiplier option: fast single-cycle or small iterative).
M0P_CYCLES: dict[str, int] = {
    **dict.fromkeys("ldr ldrh ldrb ldrsh ldrsb str strh strb".split(), 2),
}


@dataclass(frozen=True)
class CycleModel:
    """How a traced instruction stream is turned into cycles.

    Attributes
    ----------
    core : str
        "m4" (the table :data:`M4_CYCLES` and its load/store notes) or "m0plus"
        (:data:`M0P_CYCLES`).
    branch_penalty : int
        Extra cycles of a taken branch on the M4 (the TRM gives 1..3: pipeline refill).
    wait_states : int
        Flash wait states W, applied conservatively: every taken branch (a fetch from a new
        line) and every load (tables and literals are in flash; the state in RAM would pay
        nothing) costs W more. 0: code and tables in zero-wait memory or hits of a flash
        accelerator's cache.
    muls : int
        Cycles of MULS on the M0+ (1 or 32).
    """

    core: str = "m4"
    branch_penalty: int = 2
    wait_states: int = 0
    muls: int = 1

    def label(self) -> str:
        if self.core == "m4":
            return f"M4, taken branch 1+{self.branch_penalty}, {self.wait_states} wait states"
        return f"M0+, MULS {self.muls} cycles, {self.wait_states} wait states"


@dataclass(frozen=True)
class CallTrace:
    """Per call of ``update`` (and, with ``read``, of the reader that follows it): the program
    counters executed and whether each instruction was followed by a jump (a taken branch)."""

    calls: list  # of (pcs ndarray, taken ndarray of bool)
    dis: dict


def trace_calls(b: Build, samples: np.ndarray, *, read: bool = True, block: int = 0,
                timeout: float = 600.0) -> CallTrace:  # fmt: skip
    """The instruction stream of each sample: ``update`` (with the static helpers and the
    power-up decoder it calls) and, with ``read``, ``read`` after it (what a control loop pays
    per sample). ``init`` and ``clear_fault`` are not traced."""
    entry = f"{b.prefix}_q_update" if b.fixed else f"{b.prefix}_update"
    skip = ("_init", "_clear_fault", "_set_angle") + (() if read else ("_read",))
    ranges = {k: v for k, v in b.functions.items() if not k.endswith(skip)}
    start = ranges[entry][0]
    pcs = np.array(_traced_pcs(b, ranges, samples, block, timeout), dtype=np.int64)
    dis = _disassembly(b)
    size = np.array([dis.get(int(pc), ("?", "", 2))[2] for pc in pcs], dtype=np.int64)
    taken = np.ones(len(pcs), dtype=bool)
    taken[:-1] = pcs[1:] != pcs[:-1] + size[:-1]
    starts = np.flatnonzero(pcs == start)
    bounds = list(starts) + [len(pcs)]
    calls = [(pcs[a:z], taken[a:z]) for a, z in zip(bounds[:-1], bounds[1:], strict=True)]
    return CallTrace(calls, dis)


def _cost_table(dis: dict, model: CycleModel) -> dict:
    """pc -> (cost if not taken, cost if taken) under the model (the M4's pipelined-load rule
    is applied in :func:`model_cycles`)."""
    out = {}
    for pc, (mn, ops, _size) in dis.items():
        low = mn.lower().split(".")[0]
        base = _fp_base(low) if low.startswith("v") else _base(mn)
        load = base in _INT_LOADS or base in ("ldrd", "vldr", "ldm", "ldmia", "ldmdb", "vldm",
                                               "vldmia") or (base == "pop")  # fmt: skip
        w = model.wait_states if (load and base != "pop") else 0
        if model.core == "m4":
            if base in _BRANCHES:
                nt, tk = 1, 1 + model.branch_penalty
            elif base in _MULTI:
                nt = tk = 1 + _register_count(ops) + (model.branch_penalty if "pc" in ops else 0)
            elif base in M4_CYCLES:
                nt = tk = M4_CYCLES[base]
            else:
                nt = tk = 1
        else:
            if base in ("bl",):
                nt, tk = 3, 3
            elif base in _BRANCHES:
                nt, tk = 1, 2
            elif base in _MULTI:
                nt = tk = 1 + _register_count(ops) + (2 if "pc" in ops else 0)
            elif base in ("mul", "muls"):
                nt = tk = model.muls
            elif base in M0P_CYCLES:
                nt = tk = M0P_CYCLES[base]
            else:
                nt = tk = 1
        out[pc] = (nt + w, tk + w + model.wait_states, base, ops)
    return out


def model_cycles(ct: CallTrace, model: CycleModel) -> np.ndarray:
    """Cycles of each traced call under ``model`` (the M4 model applies the TRM's load/store
    notes of :func:`trace`: STR with an immediate offset 1 cycle, an integer load pipelined
    after a load 1 cycle)."""
    table = _cost_table(ct.dis, model)
    out = np.empty(len(ct.calls), dtype=np.int64)
    for k, (pcs, taken) in enumerate(ct.calls):
        c = 0
        prev_load = None
        for pc, tk in zip(pcs.tolist(), taken.tolist(), strict=True):
            nt, tkc, base, ops = table.get(pc, (1, 1, "?", ""))
            cost = tkc if tk else nt
            if model.core == "m4" and (base in _INT_LOADS or base in _INT_STORES):
                base_reg = ops.split("[", 1)[1].split(",")[0].split("]")[0].strip() if "[" in ops \
                    else ""  # fmt: skip
                if base in _INT_STORES and re.search(r"\[\w+(, #-?\d+)?\]$", ops.strip()):
                    cost -= 1  # STR Rx, [Ry, #imm] is one cycle
                elif prev_load is not None and base_reg != prev_load and base_reg != "pc":
                    cost -= 1  # pipelined with the previous load
            prev_load = ops.split(",")[0].strip() if base in _INT_LOADS else None
            c += cost
        out[k] = c
    return out
