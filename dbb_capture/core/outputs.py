"""Write outputs aside, then rename them into place, so no reader ever sees half a result."""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator

from .errors import DbbError


def _host() -> str:
    """A short tag of this machine: a pid means something only on the host that made it."""
    import hashlib
    import socket

    return hashlib.sha256(socket.gethostname().encode()).hexdigest()[:6]


def scratch_prefix(final: Path) -> str:
    """Prefix of the scratch folders beside ``final`` that this process writes (pid and host in
    the name, so a later run can tell a dead run's leftovers from a live run's work)."""
    return f".{Path(final).name}.partial-{os.getpid()}-{_host()}-"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def sweep_stale(final: Path) -> list[Path]:
    """Remove scratch (``.partial-PID-HOST-*``) and replaced (``.old-PID-HOST``) leftovers of
    ``final`` whose process on this host is gone (killed runs leave them); returns what was removed."""
    final = Path(final)
    gone = []
    if not final.parent.is_dir():
        return gone
    for p in final.parent.glob(f".{glob_escape(final.name)}.*"):
        rest = p.name[len(final.name) + 2:]
        kind, _, tail = rest.partition("-")
        pid, _, host = tail.partition("-")
        if kind in ("partial", "old") and pid.isdigit() and host[:6] == _host() and not _alive(int(pid)):
            _remove(p)
            gone.append(p)
    return gone


def glob_escape(name: str) -> str:
    return "".join(f"[{c}]" if c in "*?[" else c for c in name)


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            p.unlink()


@contextlib.contextmanager
def atomic_dir(final: Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield a scratch folder beside ``final``; on success it replaces ``final`` in one rename.

    On any exception the scratch folder is removed and ``final`` is left as it was. Leftovers
    of earlier runs that were killed (no exception reached them) are removed first, and said.
    """
    final = Path(final)
    if final.exists() and not overwrite:
        raise DbbError(f"{final} already exists (pass {{=overwrite}} to replace it)")
    check_writable(final)
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        for p in sweep_stale(final):
            from .progress import console

            console.print(f"removed {p.name}, left in {p.parent} by an earlier run that was killed", markup=False)
        tmp = Path(tempfile.mkdtemp(prefix=scratch_prefix(final), dir=final.parent))
    except OSError as e:
        raise DbbError(f"cannot write {final}: {e.strerror or e}") from None
    os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes it private; results are for sharing
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    if final.exists() or final.is_symlink():
        # Move the old result aside first: the rename below must not meet a full folder.
        old = final.parent / f".{final.name}.old-{os.getpid()}-{_host()}"
        os.replace(final, old)
    os.replace(tmp, final)
    if old is not None:
        _remove(old)


def empty_dir(path: Path) -> bool:
    """Whether ``path`` is an empty folder: one someone made for an output is no result to protect."""
    p = Path(path)
    return p.is_dir() and not any(p.iterdir())


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def check_writable(final: Path) -> None:
    """Refuse, before any work, an output ``final`` whose folder cannot be made or written
    (read-only disk, no permission, a file where a folder should be): one line instead of a late
    traceback. Makes nothing: the nearest existing ancestor is the one asked."""
    final = Path(final).absolute()
    at = final.parent
    while not at.exists() and at != at.parent:
        at = at.parent
    if not at.is_dir():
        raise DbbError(f"cannot write {final}: {at} is a file, not a folder")
    if not os.access(at, os.W_OK | os.X_OK):
        reason = "Read-only file system" if _read_only(at) else os.strerror(errno.EACCES)
        raise DbbError(f"cannot write {final}: {reason} ({at})")


def _read_only(folder: Path) -> bool:
    try:
        return bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
    except OSError:
        return False


def write_bytes_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and ``os.replace``."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    except OSError as e:
        raise DbbError(f"cannot write {path}: {e.strerror or e}") from None
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_json(path: Path, obj: Any) -> None:
    """Pretty JSON, written atomically."""
    write_bytes_atomic(Path(path), (json.dumps(obj, indent=2) + "\n").encode())


def read_json(path: Path, what: str = "file") -> Any:
    """Read JSON, turning a missing or malformed file into one clear :class:`DbbError`."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise DbbError(f"{what} not found: {path}") from None
    except json.JSONDecodeError as e:
        raise DbbError(f"{what} {path} is not valid JSON: {e.msg} at line {e.lineno}") from None
    except UnicodeDecodeError as e:
        raise DbbError(f"{what} {path} is not valid JSON: not UTF-8 text (byte {e.start})") from None
    except RecursionError:
        raise DbbError(f"{what} {path} is not valid JSON: nested too deeply") from None
    except OSError as e:
        raise DbbError(f"cannot read {what} {path}: {e.strerror or e}") from None


def run_work_dir(out: Path) -> Path:
    """Scratch folder of a training run beside ``out``: its checkpoint lives here until the run ends."""
    out = Path(out)
    return out.parent / f".{out.name}.work"


def resume_checkpoint(out: Path, name: str = "checkpoint.pt") -> Path:
    """The checkpoint ``--resume`` continues from: an interrupted run's, else the finished run's."""
    ckpt = run_work_dir(out) / name
    src = ckpt if ckpt.is_file() else Path(out) / name
    if not src.is_file():
        raise DbbError(f"nothing to resume: neither {ckpt} nor {Path(out) / name} exists")
    return src


def check_run_output(out: Path, overwrite: bool, resume: bool) -> None:
    """A training run may write ``out`` only if it is new, replaced (--overwrite) or resumed; an
    interrupted run's scratch folder (:func:`run_work_dir`) counts as the run. A replaced run's
    scratch folder is removed here, so nothing of the old run (a checkpoint, a fitted part) is
    taken for the new one's."""
    work = run_work_dir(out)
    if not (overwrite or resume):
        if Path(out).exists():
            raise DbbError(f"{out} already exists (pass {{=overwrite}} to replace it, {{=resume}} to continue it)")
        if work.exists():
            raise DbbError(f"an interrupted run of {out} is in {work} (pass {{=resume}} to continue it, "
                           f"{{=overwrite}} to start again)")
    check_writable(out)
    if overwrite and not resume and work.exists():
        shutil.rmtree(work)


def refuse_spent_budget(out: Path, steps: int | None, minutes: float | None) -> None:
    """``--resume`` of a finished run (no interrupted checkpoint beside it) whose budget ``steps``
    / ``minutes`` (counted over all its training, as a resumed run counts them) is already spent
    would train nothing and rewrite its record with a budget it never had: refused, one line."""
    out = Path(out)
    if (run_work_dir(out) / "checkpoint.pt").is_file() or not (out / "run.json").is_file():
        return      # an interrupted run finishes (its bake, its report) whatever its step
    rec = read_json(out / "run.json", "run record")
    tr = rec.get("training") if isinstance(rec, dict) else None
    if not isinstance(tr, dict) or not isinstance(tr.get("steps"), int) or not isinstance(tr.get("seconds"), (int, float)):
        return      # not a record of ours: resume_checkpoint and the trainer say what is wrong
    spent = ([f"{{=steps}} {steps}"] if steps is not None and tr["steps"] >= steps else []) + \
        ([f"{{=minutes}} {minutes:g}"] if minutes is not None and tr["seconds"] >= 60 * minutes else [])
    if spent:
        raise DbbError(f"{out} is finished ({tr['steps']} steps, {tr['seconds'] / 60:.1f} min of training) and "
                       f"{' and '.join(spent)} asks for no more: give a larger budget to train it further")


def training_minutes(minutes: float | None, steps: int | None, default: float) -> float | None:
    """The wall-clock budget of a run: ``default`` minutes when neither budget is given."""
    if (minutes is not None and minutes <= 0) or (steps is not None and steps <= 0):
        raise DbbError("{=minutes} and {=steps} must be positive")
    return default if minutes is None and steps is None else minutes
