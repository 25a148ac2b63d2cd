"""The source-keyed numba cache (fishsim.compiled): a cached compiled function is re-compiled when
a compiled function it calls from another file changes, which numba's own per-file stamp misses."""

import os
import subprocess
import sys
import textwrap

from fishsim.compiled import PACKAGE, imported_files, source_stamp

RUN = textwrap.dedent("""
    import sys
    sys.path.insert(0, sys.argv[1])
    from fishsim.compiled import register
    register(sys.argv[1] + "/calleepkg")
    from calleepkg.caller import twice
    print(twice(1.0))
""")


def _package(tmp_path, scale: float) -> None:
    pkg = tmp_path / "calleepkg"
    pkg.mkdir(exist_ok=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "callee.py").write_text(f"from fishsim.compiled import jit\n\n\n@jit\ndef scale(x):\n    return {scale} * x\n")
    (pkg / "caller.py").write_text("from fishsim.compiled import jit\nfrom calleepkg.callee import scale\n\n\n"
                                   "@jit\ndef twice(x):\n    return 2.0 * scale(x)\n")


def _run(tmp_path) -> float:
    """twice(1.0) in a fresh process, its cache beside the package (whatever NUMBA_CACHE_DIR says)."""
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    out = subprocess.run([sys.executable, "-c", RUN, str(tmp_path)], capture_output=True, text=True, check=True,
                         env=env)
    return float(out.stdout)


def test_an_edited_callee_recompiles_its_cached_caller(tmp_path):
    _package(tmp_path, 3.0)
    assert _run(tmp_path) == 6.0
    assert list((tmp_path / "calleepkg" / "__pycache__").glob("caller.twice-*.nbi")), "the caller was not cached"
    _package(tmp_path, 5.0)                          # only the callee's file changes
    assert _run(tmp_path) == 10.0


def test_the_stamp_covers_the_solid_kernels_imports():
    packed = PACKAGE / "solid" / "packed.py"
    assert ({PACKAGE / "solid" / "element.py", PACKAGE / "linalg" / "banded.py", PACKAGE / "linalg" / "simd.py"}
            <= imported_files(PACKAGE, packed))
    assert source_stamp(PACKAGE, PACKAGE / "solid" / "kernels.py") != source_stamp(PACKAGE, packed)
