"""The solver's CUDA kernels compiled without a GPU: registers and static instructions per kernel.

Issue 25: a change to a kernel can be read before device time is spent on it.

    python benchmarks/kernel_registers.py [--arch 90] [--kernels element_forces nodal_pressure ...]
                                          [--anp 1] [--visco] [--slot-table] [--gravity] [--friction]
                                          [--sliding] [--sass FILE]

Compiles ``BreastBiomechLib.solver.kernels`` for the GPU architecture ``--arch`` (sm_90: the H100
and H200) with warp's ahead-of-time compiler (NVRTC, which warp carries: no driver or GPU needed),
with the element kernels of one formulation (``kernels.element_kernels``: ``--anp`` mode, 1 ANP
within materials as the solver bench's model, 2 across, 0 none; ``--visco`` with Prony terms;
``--slot-table`` ANP slots of their own rather than the nodes, as a heterogeneous breast's) and
the node kernel of one loading (``kernels.node_kernel``: ``--gravity``, plate ``--friction``,
``--sliding`` supports; none of them by default, as the solver bench's model), reads the cubins
with ``cuobjdump`` and prints one JSON line per kernel: registers per thread and the static SASS
instructions by class (NOPs left out; ``spills``: the local-memory loads and stores a register
cap costs). Static counts cover every path of a kernel, so they are no time and no dynamic
count: they show what a change adds or removes, and the
registers decide how many threads an SM holds. On 2026-12-02 they showed a stress change raising
the batch element kernel from 96 to 106 registers, which the H200 then measured as 5-8 % slower
batches (docs/benchmarks.md).
``--sass FILE`` keeps the disassembly: a load whose value the next instructions need holds the
warp there for a whole memory round trip, predicated off or not (the node kernel's step clock
did, in every warp, until 2026-12-02; docs/benchmarks.md).

``cuobjdump`` (with its ``nvdisasm``) comes from CUDA, or from PyPI: ``pip install
nvidia-cuda-cuobjdump nvidia-cuda-nvdisasm``; it is looked for on PATH, then in the installed
``nvidia`` packages. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import collections
import importlib
import json
import os
import pkgutil
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import warp as wp

CLASSES = {
    "fp32": {"FFMA", "FMUL", "FADD", "FSETP", "FSEL", "FMNMX", "FCHK", "FSWZADD"},
    "special": {"MUFU"},
    "integer": {"IMAD", "IADD3", "SHF", "LOP3", "ISETP", "LEA", "SEL", "IABS", "IMNMX", "VIADD", "PRMT", "POPC",
                "FLO", "BREV", "IDP", "IMUL"},
    "memory": {"LDG", "STG", "LD", "ST", "LDS", "STS", "LDC", "RED", "REDG", "ATOM", "ATOMG", "ATOMS", "LDL", "STL"},
    "control": {"BRA", "EXIT", "CALL", "RET", "BSSY", "BSYNC", "WARPSYNC", "YIELD", "BAR"},
    "move": {"MOV", "HFMA2", "CS2R", "S2R", "I2F", "F2I"},  # HFMA2.MMA is a move of constants
    "uniform": {"ULDC", "UMOV", "USHF", "ULEA", "UIADD3", "UIMAD", "S2UR", "ULOP3", "UISETP", "USEL"},  # per warp
}


def find_cuobjdump() -> str:
    """cuobjdump's path, with its nvdisasm's folder put on PATH; a clear error where neither is found."""
    found = shutil.which("cuobjdump")
    if found is None:
        for base in map(Path, sys.path):
            candidates = sorted(base.glob("nvidia/cu*/bin/cuobjdump")) if base.is_dir() else []
            if candidates:
                found = str(candidates[-1])
                break
    if found is None:
        raise SystemExit("kernel_registers: cuobjdump not found; install CUDA, or "
                         "'pip install nvidia-cuda-cuobjdump nvidia-cuda-nvdisasm'")
    os.environ["PATH"] = str(Path(found).parent) + os.pathsep + os.environ.get("PATH", "")
    return found


def kernel_name(mangled: str) -> str:
    """The kernel's Python name from warp's CUDA symbol (name_hash_cuda_kernel_forward)."""
    return mangled.split("_cuda_kernel_")[0].rsplit("_", 1)[0]


def instruction_mix(sass: str) -> dict[str, dict]:
    """Per forward kernel of cuobjdump's SASS listing: the instructions (NOPs left out) by class."""
    parts = re.split(r"\n\s*Function : (\S+)", sass)
    mix = {}
    for mangled, body in zip(parts[1::2], parts[2::2]):
        if "_cuda_kernel_forward" not in mangled:
            continue
        opcodes = [re.sub(r"^@!?U?P\w+\s+", "", line).split()[0].split(".")[0]
                   for line in re.findall(r"/\*[0-9a-f]{4,}\*/\s+([^;]*);", body)]
        opcodes = [op for op in opcodes if op != "NOP"]
        counts = collections.Counter(opcodes)
        by_class = {name: sum(counts[op] for op in ops) for name, ops in CLASSES.items()}
        by_class["other"] = len(opcodes) - sum(by_class.values())
        # local-memory loads and stores (counted in "memory" too): register spills, where a kernel's
        # registers are capped below what it needs (kernels.NODE_KERNEL_REGISTERS)
        by_class["spills"] = counts["LDL"] + counts["STL"]
        mix[kernel_name(mangled)] = {"instructions": len(opcodes), **by_class}
    return mix


def registers(resources: str) -> dict[str, int]:
    """Registers per thread of each forward kernel, from ``cuobjdump -res-usage``."""
    found = re.findall(r"Function (\S+_cuda_kernel_forward):\s*\n?\s*REG:(\d+)", resources)
    return {kernel_name(mangled): int(count) for mangled, count in found}


def kernel_modules(kernels) -> list:
    """The Python modules of the solver's fixed kernels: the kernels package's submodules (since
    687432f), or the one ``kernels`` module of an older version (compared with ``PYTHONPATH=FOLDER``)."""
    if not hasattr(kernels, "__path__"):
        return [kernels]
    names = [info.name for info in pkgutil.iter_modules(kernels.__path__)]
    found = [importlib.import_module(f"{kernels.__name__}.{name}") for name in names]
    return [module for module in found if any(isinstance(value, wp.Kernel) for value in vars(module).values())]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--arch", type=int, default=90, help="GPU architecture (90: sm_90, the H100 and H200)")
    parser.add_argument("--kernels", nargs="*", default=None, help="kernels to print (default: all)")
    parser.add_argument("--anp", type=int, choices=(0, 1, 2), default=1,
                        help="the element kernels' ANP mode (kernels.ANP_*; default 1, within materials)")
    parser.add_argument("--visco", action="store_true", help="the element kernels with Prony terms")
    parser.add_argument("--slot-table", action="store_true", help="the element kernels with ANP slots of their own")
    parser.add_argument("--gravity", action="store_true", help="the node kernel with body forces")
    parser.add_argument("--friction", action="store_true", help="the node kernel with plate friction")
    parser.add_argument("--sliding", action="store_true", help="the node kernel with sliding supports")
    parser.add_argument("--sass", type=Path, default=None,
                        help="also write the compiled kernels' SASS (cuobjdump -sass) to this file")
    args = parser.parse_args()
    cuobjdump = find_cuobjdump()
    wp.config.quiet = True
    wp.init()
    from BreastBiomechLib.solver import kernels

    built = list(kernels.element_kernels(args.anp, args.visco, not args.slot_table))
    built.append(kernels.node_kernel(args.gravity, args.friction, args.sliding))
    modules = [*kernel_modules(kernels), *dict.fromkeys(kernel.module for kernel in built)]
    sass, usage = "", ""
    with tempfile.TemporaryDirectory() as folder:
        for module in modules:
            cubin = str(wp.compile_aot_module(module, device=None, arch=args.arch, module_dir=folder,
                                              use_ptx=False)[0])
            sass += subprocess.run([cuobjdump, "-sass", cubin], check=True, capture_output=True, text=True).stdout
            usage += subprocess.run([cuobjdump, "-res-usage", cubin], check=True, capture_output=True,
                                    text=True).stdout
    if args.sass is not None:
        args.sass.write_text(sass)
    regs, mixes = registers(usage), instruction_mix(sass)
    unknown = sorted(set(args.kernels or ()) - set(mixes))
    if unknown:
        raise SystemExit(f"kernel_registers: no kernel {', '.join(unknown)} in the solver's module; it has "
                         f"{', '.join(sorted(mixes))}")
    for name, mix in sorted(mixes.items()):
        if args.kernels is None or name in args.kernels:
            print(json.dumps({"kernel": name, "arch": f"sm_{args.arch}", "registers": regs.get(name), **mix}))


if __name__ == "__main__":
    main()
