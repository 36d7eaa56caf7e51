"""Helpers for the bad-input tests: a user's mistake is one line on stderr, and nothing on disk changes."""

import os


def tree(path) -> dict:
    """Every file and folder under ``path`` with size and mtime: equal before and after = nothing changed."""
    out = {}
    for root, dirs, files in os.walk(path):
        for name in dirs + files:
            p = os.path.join(root, name)
            st = os.stat(p)
            out[os.path.relpath(p, path)] = (st.st_size if name in files else 0, st.st_mtime_ns)
    return out


def one_line_error(capsys, *needles) -> str:
    """The captured stderr is one 'warpnerf: error: ...' line (Warp's CUDA notice aside) holding every needle."""
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip() and not ln.startswith("Warp CUDA")]
    assert len(err) == 1, err
    assert err[0].startswith("warpnerf: error: ") and "Traceback" not in err[0]
    for n in needles:
        assert n in err[0], (n, err[0])
    return err[0]
