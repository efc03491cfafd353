"""
A small disk that fills up: a tmpfs of a few kibibytes mounted for one test.

Mounting needs root (CAP_SYS_ADMIN), which the test machine and its CI containers have; where
the mount is refused, the tests that need a full disk are skipped with the reason.
"""

from contextlib import contextmanager
import os
import subprocess

import pytest

__all__ = ['small_disk']


@contextmanager
def small_disk(path, size_kib):
    """Mount a tmpfs of ``size_kib`` KiB on the new directory ``path``; unmount on leaving."""
    path.mkdir()
    if os.geteuid() != 0:
        pytest.skip('mounting a small tmpfs (a disk that fills up) needs root')
    mounted = subprocess.run(['mount', '-t', 'tmpfs', '-o', f'size={size_kib}k', 'tmpfs',
                              str(path)], capture_output=True, text=True)
    if mounted.returncode:
        pytest.skip(f'cannot mount a tmpfs: {mounted.stderr.strip()}')
    try:
        yield path
    finally:
        subprocess.run(['umount', '-l', str(path)], check=True)
