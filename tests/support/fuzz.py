"""Damaged inputs for the readers' fuzz tests (tests/io/test_fuzz_*.py): a valid file's bytes
with bits flipped, cut short, random bytes spliced in or written over them, or random bytes
alone. Runs are reproducible (derandomized, no example database) and small enough that all
fuzz tests together take seconds; MCL3D_FUZZ_SCALE=50 runs 50 times the examples, to search
deeper by hand."""

from __future__ import annotations

import os
from collections.abc import Callable

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from mcl3d.core.errors import Mcl3dError

DAMAGE_KINDS = ("flip", "cut", "splice", "overwrite", "random")


def fuzz_settings(examples: int) -> settings:
    """Hypothesis settings of one fuzz test: `examples` derandomized examples, no deadline."""
    scale = int(os.environ.get("MCL3D_FUZZ_SCALE", "1"))
    return settings(max_examples=examples * scale, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                           HealthCheck.function_scoped_fixture])


@st.composite
def damaged(draw, data: bytes) -> bytes:
    """`data` damaged one way (see the module docstring)."""
    kind = draw(st.sampled_from(DAMAGE_KINDS))
    if kind == "random" or not data:
        return draw(st.binary(max_size=max(64, min(len(data), 4096))))
    buf = bytearray(data)
    if kind == "flip":
        spots = st.tuples(st.integers(0, len(buf) - 1), st.integers(0, 7))
        for at, bit in draw(st.lists(spots, min_size=1, max_size=8)):
            buf[at] ^= 1 << bit
    elif kind == "cut":
        del buf[draw(st.integers(0, len(buf) - 1)):]
    else:
        at = draw(st.integers(0, len(buf)))
        junk = draw(st.binary(min_size=1, max_size=64))
        buf[at:at + (0 if kind == "splice" else len(junk))] = junk
    return bytes(buf)


def reads_or_refuses(read: Callable[[], object]) -> object | None:
    """What `read()` returns, or None when it refuses the input with an mcl3d error: anything
    else (a traceback from inside a reader) fails the test."""
    try:
        return read()
    except Mcl3dError as exc:
        assert str(exc).strip(), "an mcl3d error without a message"
        return None
