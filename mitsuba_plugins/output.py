"""Writing outputs without ever destroying a file.

Every file the package writes (EXR, PNG, tables, JSON, cache entries, plots) goes
through :func:`atomic_path`: the data is written to a temporary name in the target's
own folder and renamed over the target only once it is complete, so a failed write
(disk full, ``ulimit -f``, an interrupt) leaves the old file as it was. Commands call
:func:`check_targets` before they compute anything, so a target that cannot be written
(a folder in the way, a file where a folder should be, an unsupported extension) is
refused in one line before any work is done and before any file is touched.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import stat
import tempfile
from pathlib import Path

import numpy as np

#: temporary files being written now (removed if the process is interrupted)
PENDING: set = set()
#: ``[(temporary, target)]`` of the :func:`all_or_nothing` block under way, else None
_BATCH: list | None = None
#: what a ``null`` in our JSON outputs stands for
JSON_NULL_MEANS = "null: not a finite number (NaN or infinity, e.g. a ratio to 0), " \
                  "which JSON cannot hold"


class OutputError(ValueError):
    """An output path that cannot be written; the message names the path and why."""


def _lstat(path: Path):
    try:
        return os.lstat(path)
    except (FileNotFoundError, NotADirectoryError):  # the folder check says which
        return None
    except OSError as error:
        raise OutputError(f"output '{path}': cannot be inspected ({error.strerror})") from None


def _check_folder(folder: Path, target: Path) -> None:
    """``folder`` must be a folder or creatable: every existing ancestor is a folder."""
    for candidate in (folder, *folder.parents):
        try:
            st = os.stat(candidate)
        except FileNotFoundError:
            continue
        except OSError as error:
            raise OutputError(f"output '{target}': folder '{candidate}' cannot be used "
                              f"({error.strerror})") from None
        if not stat.S_ISDIR(st.st_mode):
            raise OutputError(f"output '{target}': '{candidate}' is a file, not a folder")
        if candidate == folder and not os.access(candidate, os.W_OK | os.X_OK):
            raise OutputError(f"output '{target}': folder '{candidate}' is not writable")
        return


def check_targets(paths, extensions: tuple | None = None, option: str = "output") -> None:
    """Refuse, before anything is written, any of ``paths`` that cannot be written:
    an extension not in ``extensions`` (lower case, with the dot), an existing folder
    or non-regular file in the way, or a file where one of its folders should be."""
    for path in map(Path, paths):
        if extensions is not None and path.suffix.lower() not in extensions:
            raise OutputError(f"{option} '{path}': extension '{path.suffix or '(none)'}' is "
                              f"not supported; allowed: {', '.join(extensions)}")
        st = _lstat(path)
        if st is not None and stat.S_ISLNK(st.st_mode):
            try:
                st = os.stat(path)
            except OSError as error:
                raise OutputError(f"{option} '{path}': a symbolic link that cannot be "
                                  f"followed ({error.strerror})") from None
        if st is not None and stat.S_ISDIR(st.st_mode):
            raise OutputError(f"{option} '{path}': a folder of that name is in the way")
        if st is not None and not stat.S_ISREG(st.st_mode):
            raise OutputError(f"{option} '{path}': exists and is not a regular file")
        _check_folder(path.parent if str(path.parent) else Path("."), path)


def check_folder_target(folder, option: str = "output") -> None:
    """An output folder: it is a folder already, or can be made."""
    folder = Path(folder)
    st = _lstat(folder)
    if st is not None and not stat.S_ISDIR(os.stat(folder).st_mode):
        raise OutputError(f"{option} '{folder}': exists and is not a folder")
    _check_folder(folder, folder)


def _mkdir(folder: Path, target: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise OutputError(f"output '{target}': a file is in the way of folder "
                          f"'{folder}'") from None
    except OSError as error:
        raise OutputError(f"output '{target}': cannot make folder '{folder}' "
                          f"({error.strerror})") from None


def _mode_for(path: Path) -> int:
    """The target's own mode if it exists, else what a new file gets under the umask."""
    try:
        return stat.S_IMODE(os.stat(path).st_mode)
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path in ``path``'s folder (same extension) to write; on
    success it is synced and renamed over ``path``, on any failure it is removed and
    ``path`` is left untouched."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    _mkdir(folder, path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{path.suffix}",
                               dir=folder)
    os.close(fd)
    PENDING.add(tmp)
    existed = path.exists()
    batch = _BATCH
    try:
        yield tmp
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, _mode_for(path))
        if batch is not None:       # renamed with the others, once all are complete
            batch.append((tmp, path))
            return
        os.replace(tmp, path)
    except Exception as error:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        reason = str(error).strip().splitlines()[-1] if str(error).strip() else \
            type(error).__name__
        if tmp in reason:   # Mitsuba's stream errors name the temporary file
            reason = reason.split(tmp, 1)[1].lstrip('": ')
        raise OutputError(f"output '{path}': could not be written ({reason}); "
                          + ("none of this command's files was written (those already "
                             "there are unchanged)" if batch is not None else
                             "the file that was there is unchanged" if existed
                             else "nothing was written")) from None
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    finally:
        if batch is None or all(t != tmp for t, _ in batch):   # else renamed with the batch
            PENDING.discard(tmp)


def staged(path) -> Path:
    """Where ``path``'s content is now: its temporary file while an
    :func:`all_or_nothing` block holds it back, else ``path``."""
    for tmp, target in _BATCH or ():
        if target == Path(path):
            return Path(tmp)
    return Path(path)


@contextlib.contextmanager
def all_or_nothing():
    """Files written through :func:`atomic_path` inside the block are renamed into place
    together at its end, or, if anything in it fails, none is (their temporary files are
    removed): a command's outputs never mix with a half-finished set (a full disk left
    ``table.md`` written and ``panel.png`` not, and then said "nothing was written")."""
    global _BATCH
    outer, _BATCH = _BATCH, []
    batch = _BATCH
    try:
        yield
    except BaseException:
        for tmp, _ in batch:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            PENDING.discard(tmp)
        raise
    finally:
        _BATCH = outer
    for tmp, path in batch:
        os.replace(tmp, path)
        PENDING.discard(tmp)


def remove_pending() -> None:
    """Delete the temporary files of writes still under way (on an interrupt)."""
    for tmp in list(PENDING):
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        PENDING.discard(tmp)


def write_text(path, text: str) -> Path:
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as f:
            f.write(text)
    return Path(path)


def json_safe(value):
    """``value`` with every non-finite float (NaN, inf) replaced by ``None``."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def dumps_json(value, **kw) -> str:
    """Strict JSON (never ``NaN``/``Infinity``): non-finite numbers become ``null``."""
    return json.dumps(json_safe(value), allow_nan=False, **kw)


def write_json(path, value, **kw) -> Path:
    return write_text(path, dumps_json(value, **kw) + "\n")


def write_exr(path, image: np.ndarray) -> Path:
    """A float32 OpenEXR image, whatever ``path``'s extension."""
    import mitsuba as mi
    bitmap = mi.Bitmap(np.ascontiguousarray(image, dtype=np.float32))
    with atomic_path(path) as tmp:
        bitmap.write(tmp, mi.Bitmap.FileFormat.OpenEXR)
    return Path(path)


def write_png(path, image: np.ndarray) -> Path:
    """An 8-bit sRGB PNG (clamped, no exposure change) of a linear image."""
    import mitsuba as mi
    bitmap = mi.Bitmap(np.ascontiguousarray(image, dtype=np.float32))
    bitmap = bitmap.convert(mi.Bitmap.PixelFormat.RGB if bitmap.channel_count() >= 3
                            else mi.Bitmap.PixelFormat.Y,
                            mi.Struct.Type.UInt8, srgb_gamma=True)
    with atomic_path(path) as tmp:
        bitmap.write(tmp, mi.Bitmap.FileFormat.PNG)
    return Path(path)


def save_figure(fig, path, **kw) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=Path(path).suffix.lstrip(".") or "png", **kw)
    return Path(path)
