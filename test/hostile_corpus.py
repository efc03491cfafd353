"""
Hostile and broken input files for the fuzz tests and ``bench/hostile_files.py``.

Everything is generated here from a seed, small on disk: resource bombs (an MCAP chunk that
declares 2 GiB, a chunk that expands 30 000 times, a frame lying about its size, a YAML
"billion laughs", 5000 nested brackets, a sparse file larger than the limits, ``/dev/zero``),
broken files (non-UTF-8, truncated gzip, random bytes, zero bytes, truncations at random
points) and bags whose metadata disagrees with their storage.
"""

from pathlib import Path
import random
import shutil
import struct
from typing import Callable, Dict, List, NamedTuple, Optional

import lz4.frame
import zstandard

MCAP_MAGIC = b'\x89MCAP0\r\n'
GiB = 1 << 30
MiB = 1 << 20


class Case(NamedTuple):
    """One hostile input: its kind (csv, params, bag), a name, and the path to give."""

    kind: str
    name: str
    path: Path


def record(opcode: int, body: bytes) -> bytes:
    """Return one MCAP record: opcode, little-endian length, body."""
    return struct.pack('<BQ', opcode, len(body)) + body


def text(value: str) -> bytes:
    data = value.encode()
    return struct.pack('<I', len(data)) + data


def chunk(declared: int, compression: str, data: bytes, crc: int = 0) -> bytes:
    """Return a chunk record declaring ``declared`` uncompressed bytes around ``data``."""
    body = struct.pack('<QQQI', 1, 2, declared, crc) + text(compression)
    return record(0x06, body + struct.pack('<Q', len(data)) + data)


def mcap_file(path: Path, *records: bytes, footer: bool = True) -> Path:
    """Write an MCAP file: magic, a ros2 header, the records, then (optionally) its end."""
    content = MCAP_MAGIC + record(0x01, text('ros2') + text('hostile_corpus')) + b''.join(records)
    if footer:
        content += record(0x0F, struct.pack('<I', 0)) + record(
            0x02, struct.pack('<QQI', 0, 0, 0)) + MCAP_MAGIC
    path.write_bytes(content)
    return path


def zeros_zstd(size: int, content_size: bool = True) -> bytes:
    """Return ``size`` zero bytes compressed with zstd (a few KB), streamed in pieces."""
    compressor = zstandard.ZstdCompressor(level=1, write_content_size=content_size)
    pieces = []
    writer = compressor.compressobj(size=size if content_size else -1)
    block = bytes(8 * MiB)
    for start in range(0, size, len(block)):
        pieces.append(writer.compress(block[:min(len(block), size - start)]))
    pieces.append(writer.flush())
    return b''.join(pieces)


def mcap_bombs(directory: Path, heavy: bool = False) -> Dict[str, Path]:
    """
    Write MCAP files whose chunks must be refused before (or while) decompressing.

    ``heavy`` also writes the issue's case: 65 KB whose zstd chunk really expands to 2 GiB
    (takes about a second to generate).
    """
    files = {
        'declares 2 GiB': mcap_file(directory / 'declares_2gib.mcap',
                                    chunk(2 * GiB, 'zstd', zeros_zstd(MiB))),
        'ratio 30000': mcap_file(directory / 'ratio.mcap', chunk(64 * MiB, 'zstd',
                                                                 zeros_zstd(64 * MiB))),
        'lying zstd frame': mcap_file(directory / 'lying_frame.mcap',
                                      chunk(1000, 'zstd', zeros_zstd(64 * MiB))),
        'lying lz4 frame': mcap_file(directory / 'lying_lz4.mcap', chunk(
            1000, 'lz4', lz4.frame.compress(bytes(16 * MiB), store_size=True))),
        'zstd without size': mcap_file(directory / 'unsized.mcap', chunk(
            1000, 'zstd', zeros_zstd(8 * MiB, content_size=False))),
        'zero records': mcap_file(directory / 'zero_records.mcap',
                                  chunk(1000, '', bytes(1000))),
        'unknown compression': mcap_file(directory / 'bz2.mcap', chunk(10, 'bz2', bytes(10))),
        'no footer': mcap_file(directory / 'no_footer.mcap',
                               chunk(2 * GiB, 'zstd', zeros_zstd(MiB)), footer=False),
    }
    if heavy:
        files['issue: 65 KB, 2 GiB of zeros'] = mcap_file(
            directory / 'issue_bomb.mcap', chunk(2 * GiB, 'zstd', zeros_zstd(2 * GiB)))
    return files


def billion_laughs(levels: int = 10) -> str:
    """Return a params file of about 400 bytes whose value expands to 9**levels strings."""
    names = 'abcdefghijklmnop'
    lines = ['a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for previous, name in zip(names, names[1:levels]):
        lines.append(f'{name}: &{name} [' + ','.join([f'*{previous}'] * 9) + ']')
    lines.append(f'ctid_node:\n  ros__parameters:\n    initial: *{names[levels - 1]}')
    return '\n'.join(lines) + '\n'


def params_cases(directory: Path, good: bytes, rng: random.Random) -> Dict[str, Path]:
    """Write hostile params files, several derived from the valid ``good``."""
    nested = 'ctid_node:\n  ros__parameters:\n    model: ' + '[' * 5000 + ']' * 5000 + '\n'
    contents = {
        'billion laughs': billion_laughs().encode(),
        '5000 nested brackets': nested.encode(),
        'sample_time 1e-12': good.replace(b'sample_time: 0.01', b'sample_time: 1.0e-12'),
        'sample_time 1e-7': good.replace(b'sample_time: 0.01', b'sample_time: 1.0e-07'),
        'binary': bytes(rng.getrandbits(8) for _ in range(3000)),
        'zero bytes': bytes(2000),
        'empty': b'',
        'latin-1': good + b'# caf\xe9\n',
        'utf-8 bom': b'\xef\xbb\xbf' + good,
        'a list': b'[1, 2, 3]\n',
        'deep mapping': ('ctid_node:\n  ros__parameters:\n' + ''.join(
            '  ' * (level + 2) + f'k{level}:\n' for level in range(60)) + '  ' * 62 + 'x: 1\n'
        ).encode(),
        'huge string': good + b'    controller: "' + b'1+' * 100_000 + b'1"\n',
    }
    for count in range(4):
        cut = rng.randrange(1, len(good))
        contents[f'truncated at {cut}'] = good[:cut]
    for count in range(4):
        flipped = bytearray(good)
        for _ in range(3):
            flipped[rng.randrange(len(flipped))] = rng.getrandbits(8)
        contents[f'flipped bytes {count}'] = bytes(flipped)
    files = {}
    for index, (name, content) in enumerate(contents.items()):
        files[name] = directory / f'params_{index}.yaml'
        files[name].write_bytes(content)
    large = directory / 'params_large.yaml'
    with open(large, 'wb') as stream:
        stream.truncate(2 * GiB)          # sparse: nothing is written
    files['2 GiB sparse'] = large
    return files


def gzip_zeros(head: bytes, byte: bytes, size: int) -> bytes:
    """Return ``head`` plus ``size`` copies of ``byte``, gzip-compressed (about 0.3 MB)."""
    import zlib

    compressor = zlib.compressobj(1, zlib.DEFLATED, 31)
    pieces = [compressor.compress(head)]
    block = byte * (8 * MiB)
    for _ in range(size // len(block)):
        pieces.append(compressor.compress(block))
    return b''.join(pieces + [compressor.flush()])


def csv_cases(directory: Path, good: bytes, rng: random.Random) -> Dict[str, Path]:
    """Write hostile CSV files, several derived from the valid ``good``."""
    import gzip

    contents = {
        'latin-1': good.replace(b'y\n', b'\xe9y\n', 1),
        'utf-8 bom': b'\xef\xbb\xbf' + good,
        'random bytes': bytes(rng.getrandbits(8) for _ in range(5000)),
        'zero bytes': bytes(5000),
        'empty': b'',
        'header only': good.split(b'\n')[0] + b'\n',
        'field of 200 000 digits': good + b'1,' + b'7' * 200_000 + b',1\n',
        'line of 2 MiB': good + b'1' * (2 * MiB) + b'\n',
        'truncated gzip': gzip.compress(good)[:len(gzip.compress(good)) // 2],
        'gzip of garbage': gzip.compress(bytes(rng.getrandbits(8) for _ in range(3000))),
        'nan cells': good + b'4.00,nan,1\n4.01,1,inf\n',
        'newlines only': b'\n' * 50_000,
        'quote never closed': good + b'1,"2,3\n' * 3,
        'semicolons': good.replace(b',', b';'),
        'decreasing time': b't,u,y\n' + b''.join(b'%d,1,%d\n' % (10 - k, k) for k in range(10)),
        'gzip bomb: one line': gzip_zeros(b't,u,y\n', b'0', 300 * MiB),
        'gzip bomb: blank lines': gzip_zeros(b't,u,y\n', b'\n', 300 * MiB),
    }
    for count in range(4):
        cut = rng.randrange(1, len(good))
        contents[f'truncated at {cut}'] = good[:cut]
    files = {}
    for index, (name, content) in enumerate(contents.items()):
        suffix = '.csv.gz' if 'gzip' in name else '.csv'
        files[name] = directory / f'data_{index}{suffix}'
        files[name].write_bytes(content)
    large = directory / 'data_large.csv'
    with open(large, 'wb') as stream:
        stream.truncate(2 * GiB)
    files['2 GiB sparse'] = large
    return files


def bag_cases(directory: Path, good_bag: Path, good_mcap: Path, rng: random.Random
              ) -> Dict[str, Path]:
    """
    Write broken bags from a good rosbag2 directory (sqlite3) and a good standalone MCAP.

    Truncations, zeroed and random bytes, a wrong schema, a metadata.yaml that disagrees with
    its storage (counts, types, compression, a missing file), a garbage or oversized
    metadata.yaml, a directory of random files; plus the MCAP bombs.
    """
    files: Dict[str, Path] = {}
    mcap = good_mcap.read_bytes()
    for count in range(4):
        cut = rng.randrange(8, len(mcap))
        files[f'mcap truncated at {cut}'] = _write(directory / f'cut_{count}.mcap', mcap[:cut])
    for count in range(3):
        damaged = bytearray(mcap)
        start = rng.randrange(len(mcap) - 64)
        damaged[start:start + 64] = bytes(rng.getrandbits(8) for _ in range(64))
        files[f'mcap random bytes at {start}'] = _write(directory / f'rnd_{count}.mcap',
                                                        bytes(damaged))
    zeroed = bytearray(mcap)
    zeroed[len(mcap) // 3:2 * len(mcap) // 3] = bytes(len(mcap) // 3 + 1)[:len(
        zeroed[len(mcap) // 3:2 * len(mcap) // 3])]
    files['mcap zeroed third'] = _write(directory / 'zeroed.mcap', bytes(zeroed))
    files['mcap zero bytes'] = _write(directory / 'zeros.mcap', bytes(4096))
    files['mcap empty'] = _write(directory / 'empty.mcap', b'')
    files['mcap wrong schema'] = _write(directory / 'schema.mcap', mcap.replace(
        b'float64 data', b'int8 data\x20\x20\x20\x20', 1))
    files['mcap random'] = _write(directory / 'random.mcap',
                                  MCAP_MAGIC + bytes(rng.getrandbits(8) for _ in range(4000)))
    edits: Dict[str, Callable[[str], str]] = {
        'metadata counts': lambda meta: meta.replace('message_count: ', 'message_count: 9', 2),
        'metadata type': lambda meta: meta.replace('std_msgs/msg/Float64', 'std_msgs/msg/Int8'),
        'metadata compressed': lambda meta: meta.replace(
            "compression_mode: ''", 'compression_mode: message').replace(
            "compression_format: ''", 'compression_format: zstd'),
        'metadata file compressed': lambda meta: meta.replace(
            "compression_mode: ''", 'compression_mode: file').replace(
            "compression_format: ''", 'compression_format: zstd'),
        'metadata missing file': lambda meta: meta.replace(
            'relative_file_paths:\n', 'relative_file_paths:\n  - gone.db3\n'),
        'metadata version 99': lambda meta: meta.replace('version: 9', 'version: 99'),
        'metadata garbage': lambda meta: billion_laughs(),
        'metadata nested': lambda meta: '[' * 5000 + ']' * 5000,
        'metadata binary': lambda meta: '\x00\x01\x02' * 100,
        'metadata empty': lambda meta: '',
    }
    for index, (name, edit) in enumerate(edits.items()):
        bag = directory / f'bag_{index}'
        shutil.copytree(good_bag, bag)
        metadata = bag / 'metadata.yaml'
        metadata.write_text(edit(metadata.read_text()))
        files[name] = bag
    database = next(good_bag.glob('*.db3'))
    for index, (name, cut) in enumerate((('db3 truncated', 0.5), ('db3 header only', 0.01))):
        bag = directory / f'db_{index}'
        shutil.copytree(good_bag, bag)
        _write(bag / database.name, database.read_bytes()[:int(database.stat().st_size * cut)])
        files[name] = bag
    bag = directory / 'db_zeroed'
    shutil.copytree(good_bag, bag)
    content = bytearray(database.read_bytes())
    content[4096:12288] = bytes(8192)
    _write(bag / database.name, bytes(content))
    files['db3 zeroed pages'] = bag
    bag = directory / 'big_metadata'
    shutil.copytree(good_bag, bag)
    with open(bag / 'metadata.yaml', 'ab') as stream:
        stream.truncate(GiB)
    files['metadata 1 GiB sparse'] = bag
    junk = directory / 'junk_dir'
    junk.mkdir()
    _write(junk / 'a.db3', bytes(rng.getrandbits(8) for _ in range(3000)))
    files['directory of random .db3'] = junk
    for name, path in mcap_bombs(directory).items():
        files[f'mcap bomb: {name}'] = path
    bomb_bag = directory / 'bomb_bag'
    shutil.copytree(good_bag, bomb_bag)
    (bomb_bag / database.name).unlink()
    shutil.copy(files['mcap bomb: declares 2 GiB'], bomb_bag / 'run.mcap')
    metadata = bomb_bag / 'metadata.yaml'
    metadata.write_text(metadata.read_text().replace(database.name, 'run.mcap').replace(
        'storage_identifier: sqlite3', 'storage_identifier: mcap'))
    files['rosbag2 directory with a chunk bomb'] = bomb_bag
    return files


def _write(path: Path, content: bytes) -> Path:
    path.write_bytes(content)
    return path


def devices() -> Dict[str, Path]:
    """Return device files that never end (absent ones left out)."""
    return {name: Path(name) for name in ('/dev/zero', '/dev/urandom') if Path(name).exists()}


def snapshot(paths: List[Path]) -> Dict[str, Optional[str]]:
    """Return the sha256 of every regular file under ``paths`` (sparse giants by size)."""
    import hashlib

    digests: Dict[str, Optional[str]] = {}
    for path in paths:
        files = sorted(path.rglob('*')) if path.is_dir() else [path]
        for file in files:
            if not file.is_file() or str(file).startswith('/dev/'):
                continue
            if file.stat().st_size > 64 * MiB:
                digests[str(file)] = f'size {file.stat().st_size}'
                continue
            digests[str(file)] = hashlib.sha256(file.read_bytes()).hexdigest()
    return digests
