"""numba's on-disk cache, keyed on every source file a compiled function can reach.

numba caches a compiled function on disk and re-compiles it when the file that defines it
changes, but not when a function it calls from another file changes: the caller's cache entry
keeps the old callee's machine code. fishsim's compiled functions are declared with ``jit``
(``numba.njit`` with ``cache=True``), and their cache entries are stamped with one hash of the
defining file and of every file of the package it imports, transitively (``source_stamp``), so
an edit anywhere in that chain re-compiles them. Compiled code may therefore call compiled code
of other files (the solid's element physics, the banded solvers), each written once.

The stamp replaces numba's per-file one through numba's cache-locator extension point (the same
cache directories as numba's: ``NUMBA_CACHE_DIR`` if set, else ``__pycache__`` beside the
source, else the user-wide cache), in files named by the stamp too; files outside the registered
packages keep numba's own.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import itertools
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numba
import numpy as np
import torch
from numba.core import caching

PACKAGE = Path(__file__).resolve().parent
_ROOTS: list[Path] = []


def _module_files(root: Path, name: str) -> list[Path]:
    """The source files of module ``name`` (dotted, absolute) if it lies in package ``root``:
    the module's .py file or its package's __init__.py (none for other packages)."""
    parts = name.split(".")
    if parts[0] != root.name or len(parts) == 1:
        return []
    path = root.joinpath(*parts[1:])
    return [f for f in (path.with_suffix(".py"), path / "__init__.py") if f.is_file()]


def imported_files(root: Path, path: Path) -> set[Path]:
    """Files of package ``root`` that the source file ``path`` imports directly (absolute
    imports; ``from pkg.a import b`` counts both pkg/a.py and a module pkg/a/b.py)."""
    names = []
    for node in ast.walk(ast.parse(path.read_bytes())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names += [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
        elif isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
    return {f for name in names for f in _module_files(root, name)}


@functools.cache
def source_stamp(root: Path, path: Path) -> str:
    """sha256 over ``path`` and the files of package ``root`` it imports, transitively (each
    file's path relative to ``root`` and its bytes, in sorted order)."""
    seen, todo = set(), [path]
    while todo:
        f = todo.pop()
        if f not in seen:
            seen.add(f)
            todo += imported_files(root, f) - seen
    digest = hashlib.sha256()
    for f in sorted(seen):
        digest.update(str(f.relative_to(root)).encode() + b"\0" + f.read_bytes())
    return digest.hexdigest()


def _root_of(py_file: str) -> Path | None:
    path = Path(py_file).resolve()
    return next((root for root in _ROOTS if path.is_relative_to(root)), None)


class _SourceKeyed:
    """Locator mixin: only for files of a registered package; stamp = ``source_stamp``."""

    def get_source_stamp(self):
        return source_stamp(self._root, Path(self._py_file).resolve())

    def get_disambiguator(self):
        """The cache files' name part: numba's (the line number) and the stamp's head, so that an
        entry of other sources is never opened (its index may pickle types that no longer exist
        where they were, which numba would fail to load before it compares the stamps)."""
        return f"{super().get_disambiguator()}-{self.get_source_stamp()[:12]}"

    @classmethod
    def from_function(cls, py_func, py_file):
        root = _root_of(py_file)
        if root is None:
            return None
        locator = super().from_function(py_func, py_file)
        if locator is not None:
            locator._root = root
        return locator


class _UserDirLocator(_SourceKeyed, caching.UserProvidedCacheLocator):
    pass


class _InTreeLocator(_SourceKeyed, caching.InTreeCacheLocator):
    pass


class _UserWideLocator(_SourceKeyed, caching.UserWideCacheLocator):
    pass


def register(root: Path) -> None:
    """Stamp the cache of every function compiled from package directory ``root`` with
    ``source_stamp`` (idempotent; the locators go first in numba's list)."""
    root = Path(root).resolve()
    if root not in _ROOTS:
        _ROOTS.append(root)
    if _UserDirLocator not in caching.CacheImpl._locator_classes:
        caching.CacheImpl._locator_classes[:0] = [_UserDirLocator, _InTreeLocator, _UserWideLocator]


register(PACKAGE)


def _launch_threads_keeping_torch_count() -> None:
    """Starts numba's thread pool now and gives torch its thread count back.

    numba's OpenMP threading layer shares torch's OpenMP runtime and, when its pool starts (at the
    first parallel kernel, or ``numba.get_num_threads``), sets that runtime's thread count to
    numba's own (NUMBA_NUM_THREADS, every core by default), and torch, once it has run an op,
    follows that count: a ``torch.set_num_threads(1)`` made before then was silently undone at
    the first frame (``OMP_NUM_THREADS`` was not: fishsim/__init__.py passes it on to numba),
    and torch split every tensor op of more than 32768 values (a 100 x 300 field's two
    components) over two threads. On a machine busy with other work such an op waited for a
    descheduled thread: 7-8 ms for a 60,000-value product in a coupled episode's backward,
    against 0.02 ms. numba sets the count only when its pool starts, and its kernels pass their
    own count to each parallel region, so starting it here and restoring torch's count keeps
    both: a later ``torch.set_num_threads`` holds."""
    count = torch.get_num_threads()
    numba.get_num_threads()
    torch.set_num_threads(count)


_launch_threads_keeping_torch_count()


def jit(*args, **options):
    """``numba.njit`` with ``cache=True`` and ``nogil=True`` (and any other njit option), stamped
    by this module. Compiled code releases the GIL, so Python threads can run it side by side
    (``in_sample_chunks``)."""
    return numba.njit(*args, cache=True, nogil=True, **options)


_thread = threading.local()


def each_sample(serial, parallel, *args) -> None:
    """Runs a compiled kernel over the samples of a batch, the first argument a batched array
    [N, ...]: ``serial`` (a loop over the samples) for one sample, which runs in the calling thread
    (a parallel region's start costs more than one sample's pass, and its spinning threads slow a
    busy machine), or in a thread of ``in_sample_chunks``, else ``parallel``, the same loop with
    ``numba.prange``. Both call one per-sample kernel whose loops are serial and in a fixed order,
    so a sample's result does not depend on its batch."""
    (serial if args[0].shape[0] == 1 or serial_here() else parallel)(*args)


def serial_here() -> bool:
    """Whether this thread runs ``serially`` (its kernels and transforms then run serially: one of
    ``in_sample_chunks``' chunks, whose parallelism they are, or work beside other work)."""
    return getattr(_thread, "serial", False)


def serially(fn, *args):
    """fn(*args) with this thread's compiled kernels and transforms serial (``serial_here``): for
    work run in a thread beside other work (``in_sample_chunks``' chunks, the rollout's background
    recomputation)."""
    _thread.serial = True
    try:
        return fn(*args)
    finally:
        _thread.serial = False


def thread_pool(threads: int, name: str) -> ThreadPoolExecutor:
    """The process's pool of ``threads`` threads named ``name`` (``in_sample_chunks``' chunks,
    the rollout's background recomputation), made on first use. One per process: a forked child
    has none of its parent's threads, and its copy of the parent's pool would queue work that
    never runs."""
    return _pool(threads, name, os.getpid())


@functools.cache
def _pool(threads: int, name: str, pid: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(threads, thread_name_prefix=name)


def sample_chunks(N: int) -> list[slice]:
    """The contiguous chunks of N samples ``in_sample_chunks`` runs: one per torch thread (at most
    N), sizes differing by at most one."""
    threads = max(1, min(torch.get_num_threads(), N))
    bounds = [N * k // threads for k in range(threads + 1)]
    return [slice(a, b) for a, b in itertools.pairwise(bounds)]


def in_sample_chunks(fn, chunks: list[slice], *args, each: list | None = None) -> list:
    """[fn(*args sliced to chunk) for chunk in chunks], the chunks run in parallel Python threads
    whose compiled kernels (``each_sample``) and DCTs are serial; a single chunk runs in the
    calling thread as it is. args: numpy arrays [N, ...] (sliced along their first axis), lists
    and tuples of them (sliced element-wise), anything else passed whole; each: one more first
    argument per chunk (e.g. what the chunk's forward kept for its backward).

    Why: numba's parallel regions leave their OpenMP threads spinning for a while after each
    one, and a batch's DCTs, whose own worker threads followed, waited for a core (in a 16-fish
    episode a DCT took 91 us a sample, alone 38-52 us). A chunk's thread runs its serial kernels
    and transforms back to back, with no hand-over between thread pools."""
    calls = [((each[k],) if each is not None else ()) + tuple(_slice(a, c) for a in args)
             for k, c in enumerate(chunks)]
    if len(chunks) == 1:
        return [fn(*calls[0])]
    jobs = [thread_pool(len(chunks), "fishsim-samples").submit(serially, fn, *call) for call in calls]
    return [job.result() for job in jobs]


def _slice(a, chunk: slice):
    if isinstance(a, np.ndarray):
        return a[chunk]
    if isinstance(a, (list, tuple)):
        return type(a)(_slice(x, chunk) for x in a)
    return a
