"""
The environment of the benchmarks' fresh processes: as an installed ctid runs for its user.

An installed package has its bytecode compiled and, after its first run of a model, that
model's derivation stored (``ctid_ros/core/model_cache.py``). :func:`user_environment` gives the
processes started inside it both, in a directory of the benchmark: bytecode written under
``PYTHONPYCACHEPREFIX`` (also where ``PYTHONDONTWRITEBYTECODE`` is set, as in some CI and
sandbox shells, which would otherwise make every fresh process compile ctid_ros again, about
80 ms) and models stored in ``CTID_CACHE_DIR``; the warm-up run of each command fills both. The
baselines run in the same environment.
"""

from contextlib import contextmanager
import os
from pathlib import Path
from typing import Dict, Iterator, Optional

__all__ = ['MODEL_STORE', 'user_environment']

MODEL_STORE = 'CTID_CACHE_DIR'


@contextmanager
def user_environment(directory: Path) -> Iterator[None]:
    """Set the variables above for the processes started within; restore them after."""
    changes = {MODEL_STORE: str(directory / 'models'),
               'PYTHONPYCACHEPREFIX': str(directory / 'bytecode'),
               'PYTHONDONTWRITEBYTECODE': None}
    saved = {name: os.environ.get(name) for name in changes}
    try:
        _set_environment(changes)
        yield
    finally:
        _set_environment(saved)


def _set_environment(values: Dict[str, Optional[str]]) -> None:
    """Set each variable to its value; remove those whose value is None."""
    for name, value in values.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value
