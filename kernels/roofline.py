"""Random-gather probe: the gather rate this machine reaches, the roofline of the grid encodings.

Warp only; launched by ``warpnerf/bench.py`` (``gather_sum``, ``gather_rate``) with the thread
split of the grid forward, so ``warpnerf bench encoding`` can say what fraction of the machine's
random-gather rate the hash-grid forward reaches.

Layout
  table  (rows,)    float32 vec2 rows, the hash grid's row type at F = 2
  rows   (N, 8)     random row ids; 8 = the corners of a 3-D cell, the gathers of one
                    (point, level) thread of the hash-grid forward
  out    (N,)       the sum of each thread's 8 rows, in column order

The row ids are read from memory rather than hashed in the kernel, so a torch twin
(``table[rows[:, 0]] + table[rows[:, 1]] + ...``) reproduces the sum bit for bit; streaming
them costs 4 sequential bytes per gather next to a random cache-line read.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

# gathers per thread: the 2^3 corners a hash-grid forward thread reads
GATHERS_PER_THREAD = 8


@wp.kernel
def gather_sum(
    table: wp.array(dtype=wp.vec2f),
    rows: wp.array2d(dtype=wp.int32),
    start: int,
    out: wp.array(dtype=wp.vec2f),
):
    i = start + wp.tid()
    acc = wp.vec2f()
    # unrolled like the grid's corner loop, so the 8 loads are independent and can overlap
    for k in range(wp.static(GATHERS_PER_THREAD)):
        acc = acc + table[rows[i, k]]
    out[i] = acc
