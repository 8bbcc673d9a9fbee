"""Mutated ASTERIX data blocks for the never-raise tests of the importers."""

from __future__ import annotations

import numpy as np


def mutants(blocks: list[bytes], rng: np.random.Generator, n: int) -> list[bytes]:
    """``n`` copies of blocks drawn from ``blocks``, each with one bit flipped, its tail cut or one
    octet deleted after the category octet, and its length field set to the new length (so the
    damage is inside the records, where a decoder must notice it)."""
    out = []
    for _ in range(n):
        b = bytearray(blocks[rng.integers(len(blocks))])
        op = rng.integers(3)
        if op == 0:
            b[rng.integers(3, len(b))] ^= 1 << rng.integers(8)
        elif op == 1:
            del b[rng.integers(4, len(b)):]
        else:
            del b[rng.integers(3, len(b))]
        b[1:3] = len(b).to_bytes(2, "big")
        out.append(bytes(b))
    return out
