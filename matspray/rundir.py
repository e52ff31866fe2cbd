"""The run directory: one object, one folder; each stage records the settings that made its artifact.

A stage is skipped when its artifact exists and was made with the same settings (its fingerprint,
which also covers the fingerprints of the stages it read from); otherwise it is recomputed and says
why. Every file is written atomically, so an interrupted run never leaves a half-written artifact.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import threading
import time
import warnings
from contextlib import contextmanager
from pathlib import Path

import yaml

from matspray.errors import MatsprayError, RunError, file_error

# callers import these from here too
from matspray.files import read_json, to_plain, write_json, write_text_atomic  # noqa: F401
from matspray.memory import peak_memory, release_free_memory
from matspray.presets import DEFAULT_ASSETS, VARIANT_NAMES, asset_stage

STAGE_RECORD = "stage.json"
DATASET_RECORD = "the dataset record `matspray run` writes"  # what dataset.json holds, for messages


def fingerprint(*parts) -> str:
    text = json.dumps([to_plain(p) for p in parts], sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def read_record(path: Path, hint: str):
    """A JSON record of a run folder, or a DataError naming it and saying what to do (`hint`) when it cannot be read."""
    path = Path(path)
    try:
        return read_json(path)
    except (OSError, ValueError) as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise file_error(path, f"is not readable JSON ({' '.join(str(exc).split())[:80]})", hint) from None


def read_mapping(path: Path, hint: str, what: str) -> dict:
    """A JSON record of a run folder that holds a mapping (`read_record`); a DataError naming it when it holds
    something else: `what` is the record it should be, e.g. "the seconds of each stage"."""
    record = read_record(path, hint)
    if not isinstance(record, dict):
        raise file_error(path, f"holds a {type(record).__name__}, not {what}", hint)
    return record


def stage_folder(path: Path) -> Path | None:
    """The stage folder of a run that `path` (a file in it, or in a subfolder of it) belongs to; None when it is no run
    artifact. A stage folder holds a stage.json and sits in a folder with a dataset.json."""
    for folder in list(Path(path).parents)[:2]:
        if (folder / STAGE_RECORD).is_file() and (folder.parent / "dataset.json").is_file():
            return folder
    return None


def stage_hint(path: Path) -> str:
    """What to do about a damaged file of a finished stage ('' when `path` is no run artifact): a stage is not trusted
    past its record, so the way out is to make it again."""
    folder = stage_folder(path)
    return "" if folder is None else f"delete {folder} and rerun `matspray run` with the same settings to make it again"


def newer_than_stages(path: Path, *run_dirs) -> bool:
    """True when `path` exists and no stage of the run folders (their `*/stage.json`) was written after it:
    a figure derived from those stages is still current."""
    path = Path(path)
    if not path.exists():
        return False
    written = path.stat().st_mtime
    return all(stage.stat().st_mtime <= written for run in run_dirs for stage in Path(run).glob(f"*/{STAGE_RECORD}"))


RUN_LOCK = "run.lock"  # inside a run folder: held by the process writing it; holds that process's id
_HELD: dict = {}  # (thread, lock file) -> [open handle, holders]: the locks this process holds, per thread


class HeldLock:
    """An exclusive `flock` on one lock file, taken by `hold_lock`; `release()` (idempotent) lets it go. Re-entrant in
    one thread: a second hold of the same file there counts up instead of blocking; other threads and processes wait or
    are refused. The kernel drops it when the process ends, however it ends, so no lock outlives its holder."""

    def __init__(self, key):
        self._key = key
        self._released = False

    def release(self) -> None:
        if self._released:
            return
        self._released = True
        entry = _HELD[self._key]
        entry[1] -= 1
        if entry[1] == 0:
            del _HELD[self._key]
            entry[0].close()  # closing the last handle drops the flock

    def __enter__(self) -> "HeldLock":
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def lock_owner(lock_file: Path) -> str:
    """The process id written into a lock file by its holder ('?' when unreadable)."""
    try:
        return Path(lock_file).read_text().strip() or "?"
    except OSError:
        return "?"


def hold_lock(lock_file: Path, wait: bool = True) -> HeldLock | None:
    """Takes the exclusive lock on `lock_file` (made if missing) and writes this process's id into it. `wait`: block
    until the holder lets go; else None at once when another thread or process holds it. Where files cannot be locked
    (no fcntl, or a file system without flock) it warns and holds nothing."""
    try:
        import fcntl  # POSIX only: imported where it is tried
    except ImportError:  # not POSIX
        fcntl = None

    lock_file = Path(lock_file)
    key = (threading.get_ident(), str(lock_file.resolve()))
    if key in _HELD:
        _HELD[key][1] += 1
        return HeldLock(key)
    lock_file.parent.mkdir(parents=True, exist_ok=True)
    handle = open(lock_file, "a+")
    try:
        if fcntl is None:
            raise OSError("no fcntl")
        fcntl.flock(handle, fcntl.LOCK_EX if wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.close()
        return None
    except OSError:  # e.g. a network mount without locks: go on, but say that nothing keeps writers apart
        warnings.warn(
            f"{lock_file}: files cannot be locked here, so nothing stops two processes from writing "
            f"{lock_file.parent} at the same time",
            stacklevel=2,
        )
    handle.seek(0)
    handle.truncate()
    handle.write(f"{os.getpid()}\n")
    handle.flush()
    _HELD[key] = [handle, 1]
    return HeldLock(key)


@contextmanager
def held_exclusively(path: Path):
    """Runs the block while holding an exclusive lock on `path`'s sidecar `path.lock`: processes that read, change and
    write back one shared file (a results table that keeps the entries of earlier passes) take turns, so none loses
    another's entries. The sidecar stays behind (removing it would race with a waiting process)."""
    path = Path(path)
    with hold_lock(path.with_name(path.name + ".lock")):
        yield


# what a dataset folder holds (matspray.data.loader reads these layouts) and a run folder does not
DATASET_FILES = ("transforms_train.json", "transforms_test.json", "transforms.json", "train_000", "sparse")


def not_a_run(root: Path) -> RunError:
    """The error for a folder without dataset.json: said to be a dataset, with the `run` that makes a run of it, when
    it holds a dataset layout; else said to be no run folder."""
    if any((Path(root) / name).exists() for name in DATASET_FILES):
        return RunError(
            f"{root}: is a dataset, not a run folder; make a run of it first with "
            f"`matspray run --data {root} --out RUN`, then give --run RUN"
        )
    return RunError(f"{root}: not a MatSpray run folder (no dataset.json); make one with `matspray run`")


class RunDir:
    def __init__(self, root):
        self.root = Path(root)

    def path(self, *parts) -> Path:
        return self.root.joinpath(*parts)

    # ---------------------------------------------------------------- who writes it
    def hold(self, wait: bool = False, notify=None) -> HeldLock:
        """Takes the run folder for this thread (its `run.lock`), so that no other process writes it at the same time;
        release the returned lock when done. Busy folder: RunError naming the process, or with `wait` block until it
        is free (`notify` hears that it waits). Holding it again in the same thread is free."""
        lock_file = self.path(RUN_LOCK)
        held = hold_lock(lock_file, wait=False)
        if held is None and wait:
            if notify is not None:
                notify(f"{self.root}: waiting for process {lock_owner(lock_file)}, which is writing this run folder")
            held = hold_lock(lock_file, wait=True)
        if held is None:
            raise RunError(
                f"{self.root}: another MatSpray process (pid {lock_owner(lock_file)}) is writing this run folder; "
                f"wait for it to finish, or use another run folder"
            )
        return held

    # ---------------------------------------------------------------- identity
    def claim(self, dataset_id: dict, overwrite: bool = False) -> None:
        """Make sure this folder belongs to the dataset described by `dataset_id` (or is new)."""
        record = self.path("dataset.json")
        if record.exists() and not overwrite:
            hint = "delete it, or allow overwriting the run folder to claim it for this dataset"
            previous = read_mapping(record, hint, DATASET_RECORD)
            if previous != to_plain(dataset_id):
                raise RunError(
                    f"{self.root}: this run folder was made from another dataset ({previous.get('source')}, "
                    f"{previous.get('train_views')} training views); "
                    "use a new run folder or allow overwriting it (overwrite)"
                )
        self.root.mkdir(parents=True, exist_ok=True)
        write_json(record, dataset_id)

    # ---------------------------------------------------------------- stages
    def stage_done(self, stage: str, stage_fingerprint: str, artifacts: list[str]) -> bool:
        record = self.path(stage, STAGE_RECORD)
        if not record.exists() or not all(self.path(stage, a).exists() for a in artifacts):
            return False
        return self.stage_fingerprint(stage) == stage_fingerprint

    def stage_fingerprint(self, stage: str) -> str | None:
        """The fingerprint a stage's record holds; None when it has none or it cannot be read (a damaged record is no
        finished stage: the stage is made again)."""
        record = self.path(stage, STAGE_RECORD)
        try:
            data = read_json(record)
        except (
            OSError,
            ValueError,
        ):  # absent, unreadable, no JSON (JSONDecodeError and UnicodeDecodeError are ValueErrors)
            return None
        value = data.get("fingerprint") if isinstance(data, dict) else None
        return value if isinstance(value, str) else None

    def finish_stage(
        self, stage: str, stage_fingerprint: str, settings, seconds: float, extra: dict | None = None, peak_mib=None
    ) -> None:
        """Writes the stage's record (last: an interrupted stage has none); `peak_mib`: the process's peak resident
        memory during the stage (`timed`), kept as `peak_memory_mib` when known."""
        memory = {} if peak_mib is None else {"peak_memory_mib": peak_mib}
        write_json(
            self.path(stage, STAGE_RECORD),
            {"fingerprint": stage_fingerprint, "settings": settings, "seconds": seconds, **memory, **(extra or {})},
        )
        self.record_timing(stage, seconds)

    def reopen_stage(self, stage: str) -> None:
        """Drop a stage's record before its files are made again: from then on the folder holds no finished stage, so
        an interruption leaves nothing that claims to be one."""
        self.path(stage, STAGE_RECORD).unlink(missing_ok=True)

    def record_timing(self, stage: str, seconds: float) -> None:
        try:
            timings = self.timings()
        except MatsprayError:  # a damaged record is replaced: it only says how long stages took
            timings = {}
        timings[stage] = round(float(seconds), 3)
        write_json(self.path("timings.json"), timings)

    def timings(self) -> dict:
        """Seconds each finished stage took (timings.json), {} when there is none."""
        path = self.path("timings.json")
        if not path.exists():
            return {}
        hint = "delete it: it only records how long each stage took, and stages made again record their time anew"
        timings = read_mapping(path, hint, "the seconds of each stage")
        for stage, seconds in timings.items():
            if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not 0 <= seconds < float("inf"):
                raise file_error(path, f"{stage}: {json.dumps(seconds)[:40]} is not a number of seconds", hint)
        return timings

    def peak_memory(self) -> dict:
        """{stage: MiB}: the peak resident memory of each timed stage whose record keeps it (runs of older versions
        and systems without /proc keep none)."""
        peaks = {}
        for stage in self.timings():
            try:
                record = read_json(self.path(stage, STAGE_RECORD))
            except (OSError, ValueError):
                continue
            value = record.get("peak_memory_mib") if isinstance(record, dict) else None
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                peaks[stage] = value
        return peaks

    def write_config(self, config) -> None:
        write_text_atomic(self.path("config.yaml"), yaml.safe_dump(to_plain(config), sort_keys=False))

    # ---------------------------------------------------------------- reads
    def require(self) -> "RunDir":
        """This folder, after checking that it is a run folder (raises RunError naming the command that makes one)."""
        if not self.path("dataset.json").exists():
            raise not_a_run(self.root)
        return self

    def config(self) -> dict:
        """The settings the run was made with (config.yaml), as plain values; {} when it has none."""
        path = self.path("config.yaml")
        if not path.exists():
            return {}
        try:
            config = yaml.safe_load(path.read_text()) or {}
        except (yaml.YAMLError, UnicodeDecodeError, OSError) as exc:
            raise file_error(
                path, f"is not readable YAML ({' '.join(str(exc).split())})", "restore it or rerun `matspray run`"
            ) from None
        if not isinstance(config, dict):
            raise file_error(
                path, f"holds a {type(config).__name__}, not the mapping of settings `matspray run` writes"
            )
        return config

    def dataset(self) -> dict:
        """The dataset identity recorded by `claim` (source folder, views, resolution)."""
        path = self.require().path("dataset.json")
        hint = "rerun `matspray run --data DATA --out RUN --overwrite` to write it again (finished stages are kept)"
        record = read_mapping(path, hint, DATASET_RECORD)
        if not isinstance(record.get("source"), str) or not record["source"] or "\0" in record["source"]:
            raise file_error(path, f"'source' is {json.dumps(record.get('source'))[:60]}, not the dataset folder", hint)
        for key in ("train_views", "test_views"):  # absent from records older than these keys
            if key in record and (
                not isinstance(record[key], list) or not all(isinstance(name, str) for name in record[key])
            ):
                raise file_error(path, f"'{key}' is not a list of view names", hint)
        return record

    def downscale(self) -> float:
        value = self.config().get("downscale", 1.0)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < 1e308:
            raise file_error(
                self.path("config.yaml"), f"downscale: {value!r} is not a number > 0", "set the factor the run used"
            )
        return float(value)

    def asset_path(self, variant: str = "full") -> Path:
        """Folder of a variant's asset; raises RunError when the run has none."""
        folder = self.path(asset_stage(variant))
        if not (folder / "asset.ply").exists():
            raise RunError(
                f"{self.root}: no asset for variant '{variant}' ({folder.name}/asset.ply); "
                f"make it with `matspray run --variant {variant}`"
            )
        return folder

    def asset_variants(self) -> list[str]:
        """The variants that have a finished asset in this run, in the registry's order."""
        return [v for v in VARIANT_NAMES if self.path(asset_stage(v), "asset.ply").exists()]

    def default_variant(self) -> str:
        """The asset a command takes when none is named: the first of `DEFAULT_ASSETS` the run has (full, else
        photos-only, the default of a run made with `--predictor none`), else the first it has; RunError when it has
        none."""
        variants = self.asset_variants()
        if not variants:
            raise RunError(
                f"{self.root}: the run has no asset yet (no asset*/asset.ply); "
                f"make it with `matspray run --data DATA --out {self.root}`"
            )
        return next((v for v in DEFAULT_ASSETS if v in variants), variants[0])


def _link_or_copy(source: str, target: str) -> None:
    try:
        os.link(source, target)
    except OSError:  # another file system
        shutil.copy2(source, target)


def share_stage(source_run, target_run, stage: str) -> bool:
    """Hard-link (else copy) the finished `stage` folder of one run folder into another that has none, so
    runs of one object share work; the target's pipeline still compares fingerprints and redoes the stage
    if they differ. False when there is nothing to share or the target has the stage already. Waits while another
    process writes the target (its run lock)."""
    source, target = Path(source_run) / stage, Path(target_run) / stage
    if not (source / STAGE_RECORD).exists():
        return False
    with RunDir(target_run).hold(wait=True):
        if (target / STAGE_RECORD).exists():
            return False
        shutil.copytree(
            source, target, copy_function=_link_or_copy, ignore=shutil.ignore_patterns(STAGE_RECORD), dirs_exist_ok=True
        )
        # the record last, as a copy written now: a half-done share is no stage, and a figure the target derived
        # from its earlier stage is older than the shared one (newer_than_stages), whatever the source's age
        write_text_atomic(target / STAGE_RECORD, (source / STAGE_RECORD).read_text())
    return True


@contextmanager
def timed():
    """`with timed() as t: ...; t.seconds, t.peak_mib` (the process's peak resident memory in the block, MiB; None
    where it cannot be measured: `matspray.memory`)."""

    class Timer:
        seconds = 0.0
        peak_mib = None

    timer = Timer()
    start = time.perf_counter()
    with peak_memory() as peak:
        try:
            yield timer
        finally:
            timer.seconds = time.perf_counter() - start
            release_free_memory()  # what the stage freed leaves the process: the next stage's peak is its own
    timer.peak_mib = peak.mib
