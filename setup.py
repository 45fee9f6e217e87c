"""Build step of the C controller core (everything else is in pyproject.toml).

At install (``pip install .`` and ``pip install -e .``) this

1. generates OSQP's embedded solver once per QP shape (controller/native/osqp_gen.py) into
   the build folder,
2. generates the cffi binding from the core's headers (controller/native/cdef_gen.py: every
   struct, constant and prototype read from the headers, offsets fixed by the compiler),
3. compiles the core (controller/native/src, ``-std=c99 -Wall -Wextra -Werror -pedantic``),
   OSQP's generated sources (their own flags: third-party code) and the binding into two
   extension modules, ``controller.native._rhcore64`` (double) and ``_rhcore32`` (float).

Where no C compiler exists (or the build fails) the install still succeeds without the
extensions, saying so in one line; the controller then runs the numpy reference and says so
in one line at start (controller/native/backend.py).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

ROOT = Path(__file__).resolve().parent
NATIVE = ROOT / "controller" / "native"
sys.path.append(str(NATIVE))  # the build helpers beside the sources (no package import; last,
# so that controller/native/config.py and controller.py shadow nothing)
import build_tools  # noqa: E402
import cdef_gen  # noqa: E402
import osqp_gen  # noqa: E402

# the core's own flags (build_tools.CFLAGS: C99, warnings as errors, IEEE) at -O3, no debug info
CORE_FLAGS = [*(f for f in build_tools.CFLAGS if not f.startswith("-O")), "-O3", "-g0"]
OSQP_FLAGS = ["-g0", "-std=gnu99", "-O3", "-w", "-ffp-contract=off"]
BINDING_FLAGS = ["-g0", "-std=c99", "-O3", "-Wall", "-Wno-missing-field-initializers",
                 "-ffp-contract=off"]
VARIANTS = {"controller.native._rhcore64": [], "controller.native._rhcore32": ["RH_FLOAT32"]}


class BuildCore(build_ext):
    """Compiles each group of sources with its own flags; never fails the install."""

    def run(self) -> None:
        if os.environ.get("RHONN_NO_CC", "") not in ("", "0"):
            print("rhonn-tv: RHONN_NO_CC is set: C core not built (the numpy reference runs)")
            return
        try:
            gen = Path(self.build_temp) / "osqp_gen"
            osqp_gen.generate(gen)
            self._gen = gen
            super().run()
        except Exception as exc:  # no compiler, a failed compile: the numpy reference runs
            print(f"rhonn-tv: C core not built ({type(exc).__name__}: "
                  f"{str(exc).strip().splitlines()[-1] if str(exc).strip() else exc}); "
                  f"the numpy reference runs")

    def _osqp_objects(self, inc_osqp: list[str]) -> list[str]:
        """OSQP's generated sources compiled once for both extensions (no variant define
        reaches them: the double and the float core link the same solver objects)."""
        if getattr(self, "_osqp_objs", None) is None:
            self._osqp_objs = self.compiler.compile(
                [str(p) for p in osqp_gen.osqp_sources(self._gen)],
                output_dir=str(Path(self.build_temp) / "osqp"),
                include_dirs=inc_osqp, extra_postargs=OSQP_FLAGS)
        return self._osqp_objs

    def build_extension(self, ext: Extension) -> None:
        gen, og = self._gen, osqp_gen
        defines = [(d, None) for d in VARIANTS[ext.name]]
        tmp = Path(self.build_temp) / ext.name
        inc_osqp = [str(p) for p in og.osqp_include_dirs(gen)]
        inc_core = [str(NATIVE / "include"), str(NATIVE / "src")]
        isystem = [f"-isystem{p}" for p in inc_osqp]
        objs = self.compiler.compile(
            [str(p) for p in sorted((NATIVE / "src").glob("*.c"))], output_dir=str(tmp / "core"),
            macros=defines, include_dirs=inc_core, extra_postargs=CORE_FLAGS + isystem)
        objs += self._osqp_objects(inc_osqp)
        binding = cdef_gen.emit_binding(ext.name, [NATIVE / "include", NATIVE / "src"],
                                        VARIANTS[ext.name], tmp / "binding" / "module.c")
        objs += self.compiler.compile(
            [str(binding)], output_dir=str(tmp / "binding"),
            macros=defines, include_dirs=inc_core, extra_postargs=BINDING_FLAGS + isystem)
        self.compiler.link_shared_object(
            objs, self.get_ext_fullpath(ext.name), libraries=["m"],
            export_symbols=self.get_export_symbols(ext),
            build_temp=str(tmp), target_lang="c")


setup(ext_modules=[Extension(name, sources=[]) for name in VARIANTS],
      cmdclass={"build_ext": BuildCore})
