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


# Warp's own notices on the first use of Warp in a process, not ours: no CUDA driver, and kernels of another
# Warp version in the kernel cache
_WARP_NOTICES = ("Warp CUDA", "Warp UserWarning: Kernel cache artifacts")


def error_lines(stderr: str) -> list[str]:
    """The non-empty lines of ``stderr``, Warp's own start-up notices left out."""
    return [ln for ln in stderr.splitlines() if ln.strip() and not ln.startswith(_WARP_NOTICES)]


def one_line_error(capsys, *needles, prefix: str = "warpnerf: error: ") -> str:
    """The captured stderr is one line starting with ``prefix`` (Warp's notices aside) holding every needle."""
    err = error_lines(capsys.readouterr().err)
    assert len(err) == 1, err
    assert err[0].startswith(prefix) and "Traceback" not in err[0]
    for n in needles:
        assert n in err[0], (n, err[0])
    return err[0]
