"""What a run's numbers depend on besides its scenario: this project's code and the numerical packages underneath.

Runs are seeded, so the same scenario gives the same bits wherever it runs, but only with the same code and the
same numerical libraries: a Dask worker with another numpy, casadi or an older checkout of this project would give
other numbers without any error. `environment()` is the fingerprint a worker reports with each result and that
`sitl.experiments.distributed` compares with the asking process's own. Not covered: the CPU's own instruction set
(numpy picks SIMD kernels per CPU; a cluster of one processor kind is the safe choice).
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
import json
import platform
from pathlib import Path

PROJECT_PACKAGES = ("behaviors", "bob_autonomy", "firmware_bridge", "sitl")
# The packages whose arithmetic ends up in a run's figures (pydantic, tqdm, matplotlib and dask do not).
NUMERICAL_PACKAGES = ("numpy", "scipy", "casadi", "filterpy", "pymavlink", "fastcrc")
SOURCE_SUFFIXES = (".py", ".toml")  # the code and the packaged scenario files
SOURCE_KEY = "bob-autonomy source"

_ENVIRONMENT: dict[str, str] | None = None  # worked out once per process


def environment() -> dict[str, str]:
    """This process's fingerprint: Python's version and machine, each numerical package's version and a digest of
    this project's source files (name -> value, all strings). Computed once per process (about 30 ms)."""
    global _ENVIRONMENT
    if _ENVIRONMENT is None:
        found = {"python": platform.python_version(), "machine": platform.machine()}
        for name in NUMERICAL_PACKAGES:
            try:
                found[name] = importlib.metadata.version(name)
            except importlib.metadata.PackageNotFoundError:
                found[name] = "not installed"
        found[SOURCE_KEY] = source_digest()
        _ENVIRONMENT = found
    return _ENVIRONMENT


def source_digest() -> str:
    """SHA-256 (first 16 hex digits) over every source and scenario file of this project's packages, by path
    within its package and contents: equal digests, equal code, whether installed or run from a checkout."""
    digest = hashlib.sha256()
    for package in PROJECT_PACKAGES:
        spec = importlib.util.find_spec(package)
        if spec is None or not spec.submodule_search_locations:
            digest.update(f"{package} missing\0".encode())
            continue
        root = Path(next(iter(spec.submodule_search_locations)))
        files = sorted(p for p in root.rglob("*") if p.suffix in SOURCE_SUFFIXES and p.is_file())
        for path in files:
            digest.update(f"{package}/{path.relative_to(root).as_posix()}\0".encode())
            digest.update(path.read_bytes())
            digest.update(b"\0")
    return digest.hexdigest()[:16]


def differences(here: dict[str, str], there: dict[str, str]) -> list[str]:
    """What differs between two fingerprints, as "numpy 1.26.4 there, 2.1.3 here" (empty when they agree)."""
    keys = list(here) + [key for key in there if key not in here]
    return [
        f"{key} {there.get(key, 'unknown')} there, {here.get(key, 'unknown')} here"
        for key in keys
        if here.get(key) != there.get(key)
    ]


def write_environment(directory: Path) -> None:
    """environment.json in `directory`: the fingerprint of the code and libraries that made its runs (a sweep's
    workers were checked against it, and so were the runs a resumed sweep kept)."""
    text = json.dumps(environment(), indent=2) + "\n"
    (Path(directory) / "environment.json").write_text(text, encoding="utf-8")
