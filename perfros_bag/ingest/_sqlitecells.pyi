"""Types of the C extension built from ``_sqlitecells.c`` (see that file for the contract)."""

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

_I64 = npt.NDArray[np.int64]

class Malformed(ValueError): ...

def decode(buf: object, root: int, page_size: int, usable: int, topic: _I64, time: _I64,
           size: _I64, release: Callable[[int, int], object] | None, release_step: int) -> int: ...

def decode_heads(buf: object, root: int, page_size: int, usable: int, topic: _I64, time: _I64,
                 size: _I64, release: Callable[[int, int], object] | None, release_step: int,
                 want: _I64, heads: npt.NDArray[np.uint8], rows: _I64) -> tuple[int, int]: ...

def group(tids: _I64, times: _I64, sizes: _I64, ids: _I64, counts: _I64, nbytes: _I64,
          out_times: _I64) -> bool: ...
