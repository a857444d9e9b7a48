"""Ways to spoil a dataset file the way disks, copies and foreign writers do, for the tests of bad data."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np


def damage_chunk(path: Path, split: str, index: int) -> None:
    """Overwrite bytes in the middle of trajectory ``index``'s compressed chunk of ``split/fields``.

    The header and the chunk index stay intact, so the file opens and validates; decompressing that chunk
    fails (zlib's checksum), as h5py's ``filter returned failure during read``.
    """
    with h5py.File(path, "r") as f:
        fields = f[f"{split}/fields"]
        assert fields.compression == "gzip" and fields.chunks[0] == 1
        chunks = [fields.id.get_chunk_info(i) for i in range(fields.id.get_num_chunks())]
    chunk = next(c for c in chunks if c.chunk_offset[0] == index)
    with open(path, "r+b") as fh:
        fh.seek(chunk.byte_offset + chunk.size // 2)
        fh.write(b"\xff" * 16)


def put_nonfinite(path: Path, split: str, index: int, frame: int, channel: int, value: float = np.nan) -> None:
    """Write ``value`` (NaN, inf) into one cell of one frame of one channel, as a faulty writer would."""
    with h5py.File(path, "a") as f:
        f[f"{split}/fields"][index, frame, channel, 3] = value
