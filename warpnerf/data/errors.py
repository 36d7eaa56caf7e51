"""The one exception type of the data layer."""


class DatasetError(ValueError):
    """A scene cannot be found, read or generated.

    The message is a single line naming the file, folder or key at fault (and, where it helps,
    what to do), so the CLI can print it as is without a traceback.
    """


def check_c2w(m, where: str, tol: float = 1e-3) -> None:
    """Raise DatasetError unless ``m`` (3x4 or 4x4, any array-like) is a finite camera-to-world
    matrix whose 3x3 block is a proper rotation (orthonormal within ``tol``, det +1).

    A NaN pose is not just one bad view: LLFF recentring spreads it to every pose and the marcher
    then walks an infinite ray, so it has to be stopped here, before anything is written.
    """
    import numpy as np

    a = np.asarray(m, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise DatasetError(f"{where} has non-finite values (NaN or inf)")
    r = a[:3, :3]
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > tol:
        raise DatasetError(f"{where}: rotation is not orthonormal (max |R^T R - I| = {err:.3g} > {tol})")
    det = float(np.linalg.det(r))
    if det < 0:
        raise DatasetError(f"{where}: rotation is a reflection (det = {det:.3f}, expected +1)")
