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
import statistics
import subprocess
import time
from typing import Dict, Iterator, List, Mapping, Optional, Tuple

__all__ = ['MODEL_STORE', 'interleaved_medians', 'time_process', 'user_environment']

MODEL_STORE = 'CTID_CACHE_DIR'
_REPOSITORY = Path(__file__).resolve().parent.parent


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


def time_process(command: List[str]) -> Tuple[float, float]:
    """Return the wall and CPU seconds (user + system of the child) of one fresh process."""
    before = os.times()
    started = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                   cwd=_REPOSITORY)
    wall = time.perf_counter() - started
    after = os.times()
    return wall, (after.children_user - before.children_user
                  + after.children_system - before.children_system)


def interleaved_medians(commands: Mapping[str, List[str]], runs: int
                        ) -> Dict[str, Tuple[float, float]]:
    """
    Return the median (wall, CPU) seconds of each command over ``runs`` interleaved runs.

    Each command runs once first, untimed, to warm the file cache, the bytecode and the model
    store; then the commands take turns, so load that comes and goes falls on all alike.
    """
    for command in commands.values():
        time_process(command)
    times: Dict[str, List[Tuple[float, float]]] = {name: [] for name in commands}
    for _ in range(runs):
        for name, command in commands.items():
            times[name].append(time_process(command))
    return {name: (statistics.median(w for w, _ in values),
                   statistics.median(c for _, c in values)) for name, values in times.items()}
