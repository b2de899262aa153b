"""The registry: one SQLite file in the data directory that knows the models, the build
jobs, the access tokens and (for design reviews) the review sessions.

WAL mode (readers never wait for the writer), one connection shared under a lock (every
statement is short), schema versioned by `PRAGMA user_version` with forward migrations,
so a later release opens an older file and upgrades it in place. The registry never
points at a model file that is not there: `reconcile()` checks at start.
"""

from __future__ import annotations

import json
import logging
import sqlite3
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger("vastray.registry")

REGISTRY_FILE = "registry.sqlite3"

# Migration k brings a file from schema version k to k + 1.
MIGRATIONS: tuple[str, ...] = (
    """
    CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
    CREATE TABLE models (
        id TEXT PRIMARY KEY,
        name TEXT NOT NULL,
        state TEXT NOT NULL CHECK (state IN ('building', 'ready', 'deleting')),
        file TEXT,
        source TEXT,
        job_id TEXT,
        created_at REAL NOT NULL,
        info TEXT NOT NULL DEFAULT '{}'
    );
    CREATE TABLE jobs (
        id TEXT PRIMARY KEY,
        kind TEXT NOT NULL DEFAULT 'build',
        model_id TEXT,
        name TEXT NOT NULL,
        source TEXT NOT NULL,
        state TEXT NOT NULL
            CHECK (state IN ('queued', 'running', 'succeeded', 'failed', 'cancelled', 'interrupted')),
        phase TEXT,
        percent REAL NOT NULL DEFAULT 0,
        eta_seconds REAL,
        message TEXT,
        error TEXT,
        options TEXT NOT NULL DEFAULT '{}',
        report TEXT,
        created_at REAL NOT NULL,
        started_at REAL,
        finished_at REAL
    );
    CREATE INDEX jobs_by_state ON jobs (state);
    CREATE TABLE job_log (
        job_id TEXT NOT NULL,
        seq INTEGER NOT NULL,
        at REAL NOT NULL,
        line TEXT NOT NULL,
        PRIMARY KEY (job_id, seq)
    );
    CREATE TABLE tokens (
        id TEXT PRIMARY KEY,
        secret_hash TEXT NOT NULL,
        scope TEXT NOT NULL CHECK (scope IN ('model', 'review')),
        subject TEXT NOT NULL,
        role TEXT,
        label TEXT,
        created_at REAL NOT NULL,
        expires_at REAL NOT NULL
    );
    CREATE INDEX tokens_by_subject ON tokens (scope, subject);
    CREATE TABLE reviews (
        id TEXT PRIMARY KEY,
        model_id TEXT NOT NULL,
        title TEXT NOT NULL,
        created_at REAL NOT NULL,
        state TEXT NOT NULL DEFAULT '{}'
    );
    """,
    # 2: what design reviews keep.
    """
    CREATE TABLE annotations (
        id TEXT PRIMARY KEY,
        review_id TEXT NOT NULL REFERENCES reviews (id) ON DELETE CASCADE,
        author TEXT,
        text TEXT NOT NULL,
        position TEXT NOT NULL,
        camera TEXT,
        created_at REAL NOT NULL
    );
    CREATE INDEX annotations_by_review ON annotations (review_id, created_at);
    CREATE TABLE saved_views (
        id TEXT PRIMARY KEY,
        review_id TEXT NOT NULL REFERENCES reviews (id) ON DELETE CASCADE,
        name TEXT NOT NULL,
        state TEXT NOT NULL,
        created_at REAL NOT NULL
    );
    CREATE INDEX saved_views_by_review ON saved_views (review_id, created_at);
    """,
    # 3: which way is up in a model (JSON [x, y, z]; NULL: +y), set by PATCH.
    """
    ALTER TABLE models ADD COLUMN up TEXT;
    """,
    # 4: views saved with a model (camera, sections, highlight), outside any review.
    """
    CREATE TABLE model_views (
        id TEXT PRIMARY KEY,
        model_id TEXT NOT NULL REFERENCES models (id) ON DELETE CASCADE,
        name TEXT NOT NULL,
        state TEXT NOT NULL,
        created_at REAL NOT NULL
    );
    CREATE INDEX model_views_by_model ON model_views (model_id, created_at);
    """,
    # 5: the length unit of a model's coordinates (NULL: not said), set by PATCH.
    """
    ALTER TABLE models ADD COLUMN units TEXT;
    """,
)
SCHEMA_VERSION = len(MIGRATIONS)
JOB_LOG_KEEP = 200  # lines kept per job


class RegistryError(RuntimeError):
    pass


@dataclass
class ModelRow:
    id: str
    name: str
    state: str
    file: str | None
    source: str | None
    job_id: str | None
    created_at: float
    info: dict[str, Any]
    up: tuple[float, float, float] | None = None  # None: +y
    units: str | None = None  # None: not said


@dataclass
class JobRow:
    id: str
    kind: str
    model_id: str | None
    name: str
    source: str
    state: str
    phase: str | None
    percent: float
    eta_seconds: float | None
    message: str | None
    error: str | None
    options: dict[str, Any]
    report: dict[str, Any] | None
    created_at: float
    started_at: float | None
    finished_at: float | None


@dataclass
class TokenRow:
    id: str
    secret_hash: str
    scope: str
    subject: str
    role: str | None
    label: str | None
    created_at: float
    expires_at: float


def _model(row: sqlite3.Row) -> ModelRow:
    d = dict(row)
    d["info"] = json.loads(d["info"] or "{}")
    d["up"] = tuple(json.loads(d["up"])) if d["up"] else None
    return ModelRow(**d)


def _saved_view(row: sqlite3.Row) -> dict[str, Any]:
    """A review's or a model's saved view, its state decoded."""
    return {**dict(row), "state": json.loads(row["state"])}


def _job(row: sqlite3.Row) -> JobRow:
    d = dict(row)
    d["options"] = json.loads(d["options"] or "{}")
    d["report"] = json.loads(d["report"]) if d["report"] else None
    return JobRow(**d)


class Registry:
    def __init__(self, data_dir: Path) -> None:
        self.path = data_dir / REGISTRY_FILE
        self._lock = threading.RLock()
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None, timeout=30.0)
        self._db.row_factory = sqlite3.Row
        self._db.execute("PRAGMA journal_mode=WAL")
        # NORMAL in WAL mode: a power cut may lose the last commits, never corrupt the file.
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.execute("PRAGMA foreign_keys=ON")
        self._migrate()

    # -- plumbing --------------------------------------------------------------------------

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                yield self._db
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")

    def _query(self, sql: str, args: tuple[Any, ...] = ()) -> list[sqlite3.Row]:
        with self._lock:
            return self._db.execute(sql, args).fetchall()

    def _migrate(self) -> None:
        with self._lock:
            version = self._db.execute("PRAGMA user_version").fetchone()[0]
            if version > SCHEMA_VERSION:
                raise RegistryError(
                    f"{self.path}: registry schema version {version} is newer than this vastray "
                    f"understands ({SCHEMA_VERSION}); upgrade vastray or use another data directory"
                )
            if version == 0:
                log.info("registry: new at %s (schema %d)", self.path, SCHEMA_VERSION)
            for v in range(version, SCHEMA_VERSION):
                if version > 0:  # a new registry runs every step: nothing to tell
                    log.info("registry: migrating schema %d -> %d", v, v + 1)
                # executescript commits first; run each migration as one transaction.
                self._db.executescript(
                    f"BEGIN IMMEDIATE;\n{MIGRATIONS[v]}\nPRAGMA user_version = {v + 1};\nCOMMIT;"
                )
            if version == 0:
                self.set_meta("created_at", str(time.time()))

    @property
    def schema_version(self) -> int:
        return int(self._query("PRAGMA user_version")[0][0])

    def close(self) -> None:
        with self._lock:
            self._db.close()

    # -- meta ------------------------------------------------------------------------------

    def get_meta(self, key: str) -> str | None:
        rows = self._query("SELECT value FROM meta WHERE key = ?", (key,))
        return rows[0][0] if rows else None

    def set_meta(self, key: str, value: str) -> None:
        with self._tx() as db:
            db.execute(
                "INSERT INTO meta (key, value) VALUES (?, ?) ON CONFLICT(key) DO UPDATE SET value = ?",
                (key, value, value),
            )

    # -- models ----------------------------------------------------------------------------

    def add_model(self, row: ModelRow) -> None:
        with self._tx() as db:
            db.execute(
                "INSERT INTO models (id, name, state, file, source, job_id, created_at, info, up) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    row.id,
                    row.name,
                    row.state,
                    row.file,
                    row.source,
                    row.job_id,
                    row.created_at,
                    json.dumps(row.info),
                    json.dumps(list(row.up)) if row.up else None,
                ),
            )

    def model(self, model_id: str) -> ModelRow | None:
        rows = self._query("SELECT * FROM models WHERE id = ?", (model_id,))
        return _model(rows[0]) if rows else None

    def models(self, states: tuple[str, ...] = ("building", "ready")) -> list[ModelRow]:
        marks = ",".join("?" * len(states))
        rows = self._query(f"SELECT * FROM models WHERE state IN ({marks}) ORDER BY created_at", states)
        return [_model(r) for r in rows]

    def update_model(self, model_id: str, **fields: Any) -> None:
        if "info" in fields:
            fields["info"] = json.dumps(fields["info"])
        if fields.get("up") is not None:
            fields["up"] = json.dumps(list(fields["up"]))
        sets = ", ".join(f"{k} = ?" for k in fields)
        with self._tx() as db:
            db.execute(f"UPDATE models SET {sets} WHERE id = ?", (*fields.values(), model_id))

    def delete_model(self, model_id: str) -> None:
        with self._tx() as db:
            db.execute("DELETE FROM models WHERE id = ?", (model_id,))
            db.execute("DELETE FROM tokens WHERE scope = 'model' AND subject = ?", (model_id,))
            # Reviews of the model go with it (annotations and saved views cascade).
            db.execute(
                "DELETE FROM tokens WHERE scope = 'review' "
                "AND subject IN (SELECT id FROM reviews WHERE model_id = ?)",
                (model_id,),
            )
            db.execute("DELETE FROM reviews WHERE model_id = ?", (model_id,))

    # -- jobs ------------------------------------------------------------------------------

    def add_job(self, row: JobRow) -> None:
        with self._tx() as db:
            db.execute(
                "INSERT INTO jobs (id, kind, model_id, name, source, state, phase, percent, eta_seconds, "
                "message, error, options, report, created_at, started_at, finished_at) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    row.id,
                    row.kind,
                    row.model_id,
                    row.name,
                    row.source,
                    row.state,
                    row.phase,
                    row.percent,
                    row.eta_seconds,
                    row.message,
                    row.error,
                    json.dumps(row.options),
                    json.dumps(row.report) if row.report is not None else None,
                    row.created_at,
                    row.started_at,
                    row.finished_at,
                ),
            )

    def job(self, job_id: str) -> JobRow | None:
        rows = self._query("SELECT * FROM jobs WHERE id = ?", (job_id,))
        return _job(rows[0]) if rows else None

    def jobs(self, states: tuple[str, ...] | None = None, limit: int = 200) -> list[JobRow]:
        if states:
            marks = ",".join("?" * len(states))
            rows = self._query(
                f"SELECT * FROM jobs WHERE state IN ({marks}) ORDER BY created_at DESC LIMIT ?",
                (*states, limit),
            )
        else:
            rows = self._query("SELECT * FROM jobs ORDER BY created_at DESC LIMIT ?", (limit,))
        return [_job(r) for r in rows]

    def update_job(self, job_id: str, **fields: Any) -> None:
        for key in ("options", "report"):
            if key in fields and fields[key] is not None:
                fields[key] = json.dumps(fields[key])
        sets = ", ".join(f"{k} = ?" for k in fields)
        with self._tx() as db:
            db.execute(f"UPDATE jobs SET {sets} WHERE id = ?", (*fields.values(), job_id))

    def job_counts(self) -> dict[str, int]:
        return {r[0]: r[1] for r in self._query("SELECT state, COUNT(*) FROM jobs GROUP BY state")}

    def append_log(self, job_id: str, lines: list[str]) -> None:
        now = time.time()
        with self._tx() as db:
            last = db.execute(
                "SELECT COALESCE(MAX(seq), -1) FROM job_log WHERE job_id = ?", (job_id,)
            ).fetchone()[0]
            db.executemany(
                "INSERT INTO job_log (job_id, seq, at, line) VALUES (?, ?, ?, ?)",
                [(job_id, last + 1 + i, now, line) for i, line in enumerate(lines)],
            )
            db.execute(
                "DELETE FROM job_log WHERE job_id = ? AND seq <= ?",
                (job_id, last + len(lines) - JOB_LOG_KEEP),
            )

    def job_log(self, job_id: str, tail: int = JOB_LOG_KEEP) -> list[str]:
        rows = self._query(
            "SELECT line FROM (SELECT seq, line FROM job_log WHERE job_id = ? ORDER BY seq DESC LIMIT ?) "
            "ORDER BY seq",
            (job_id, tail),
        )
        return [r[0] for r in rows]

    # -- tokens ----------------------------------------------------------------------------

    def add_token(self, row: TokenRow) -> None:
        with self._tx() as db:
            db.execute(
                "INSERT INTO tokens (id, secret_hash, scope, subject, role, label, created_at, expires_at) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    row.id,
                    row.secret_hash,
                    row.scope,
                    row.subject,
                    row.role,
                    row.label,
                    row.created_at,
                    row.expires_at,
                ),
            )

    def token(self, token_id: str) -> TokenRow | None:
        rows = self._query("SELECT * FROM tokens WHERE id = ?", (token_id,))
        return TokenRow(**dict(rows[0])) if rows else None

    def delete_expired_tokens(self, now: float) -> int:
        with self._tx() as db:
            return db.execute("DELETE FROM tokens WHERE expires_at < ?", (now,)).rowcount

    # -- reviews ---------------------------------------------------------------------------

    def add_review(
        self, review_id: str, model_id: str, title: str, state: dict[str, Any] | None = None
    ) -> None:
        """`state`: where its shared view starts (as update_review_state keeps it)."""
        with self._tx() as db:
            db.execute(
                "INSERT INTO reviews (id, model_id, title, created_at, state) VALUES (?, ?, ?, ?, ?)",
                (review_id, model_id, title, time.time(), json.dumps(state or {})),
            )

    def review(self, review_id: str) -> dict[str, Any] | None:
        rows = self._query("SELECT * FROM reviews WHERE id = ?", (review_id,))
        if not rows:
            return None
        d = dict(rows[0])
        d["state"] = json.loads(d["state"] or "{}")
        return d

    def reviews(self) -> list[dict[str, Any]]:
        return [
            dict(r)
            for r in self._query("SELECT id, model_id, title, created_at FROM reviews ORDER BY created_at")
        ]

    def update_review_state(self, review_id: str, state: dict[str, Any]) -> None:
        with self._tx() as db:
            db.execute("UPDATE reviews SET state = ? WHERE id = ?", (json.dumps(state), review_id))

    def delete_review(self, review_id: str) -> None:
        with self._tx() as db:
            db.execute("DELETE FROM reviews WHERE id = ?", (review_id,))
            db.execute("DELETE FROM tokens WHERE scope = 'review' AND subject = ?", (review_id,))

    def add_annotation(
        self,
        note_id: str,
        review_id: str,
        author: str | None,
        text: str,
        position: list[float],
        camera: dict[str, Any] | None,
    ) -> None:
        with self._tx() as db:
            db.execute(
                "INSERT INTO annotations (id, review_id, author, text, position, camera, created_at) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)",
                (note_id, review_id, author, text, json.dumps(position), json.dumps(camera), time.time()),
            )

    def annotations(self, review_id: str) -> list[dict[str, Any]]:
        rows = self._query("SELECT * FROM annotations WHERE review_id = ? ORDER BY created_at", (review_id,))
        out = []
        for r in rows:
            d = dict(r)
            d["position"] = json.loads(d["position"])
            d["camera"] = json.loads(d["camera"]) if d["camera"] else None
            out.append(d)
        return out

    def delete_annotation(self, review_id: str, note_id: str) -> bool:
        with self._tx() as db:
            return (
                db.execute(
                    "DELETE FROM annotations WHERE review_id = ? AND id = ?", (review_id, note_id)
                ).rowcount
                > 0
            )

    def add_saved_view(self, view_id: str, review_id: str, name: str, state: dict[str, Any]) -> None:
        with self._tx() as db:
            db.execute(
                "INSERT INTO saved_views (id, review_id, name, state, created_at) VALUES (?, ?, ?, ?, ?)",
                (view_id, review_id, name, json.dumps(state), time.time()),
            )

    def saved_views(self, review_id: str) -> list[dict[str, Any]]:
        rows = self._query("SELECT * FROM saved_views WHERE review_id = ? ORDER BY created_at", (review_id,))
        return [_saved_view(r) for r in rows]

    # -- views saved with a model ----------------------------------------------------------

    def add_model_view(
        self, view_id: str, model_id: str, name: str, state: dict[str, Any], most: int
    ) -> dict[str, Any] | None:
        """The view as `model_views` lists it; None (and nothing saved) when the model has
        `most` views already."""
        row = {"id": view_id, "model_id": model_id, "name": name, "state": state, "created_at": time.time()}
        with self._tx() as db:
            count_sql = "SELECT COUNT(*) FROM model_views WHERE model_id = ?"
            if db.execute(count_sql, (model_id,)).fetchone()[0] >= most:
                return None
            db.execute(
                "INSERT INTO model_views (id, model_id, name, state, created_at) VALUES (?, ?, ?, ?, ?)",
                (view_id, model_id, name, json.dumps(state), row["created_at"]),
            )
        return row

    def model_views(self, model_id: str) -> list[dict[str, Any]]:
        rows = self._query("SELECT * FROM model_views WHERE model_id = ? ORDER BY created_at", (model_id,))
        return [_saved_view(r) for r in rows]

    def delete_model_view(self, model_id: str, view_id: str) -> bool:
        with self._tx() as db:
            gone = db.execute("DELETE FROM model_views WHERE model_id = ? AND id = ?", (model_id, view_id))
            return gone.rowcount > 0

    # -- start-up checks -------------------------------------------------------------------

    def reconcile(self, data_dir: Path) -> dict[str, list[str]]:
        """Brings the registry in line with the disk after a restart or a crash: jobs
        that were queued or running are marked interrupted; models being built by them
        are forgotten; models marked for deletion are deleted; models whose file is gone
        are forgotten (and said so). Returns what was done, for the log."""
        done: dict[str, list[str]] = {"interrupted": [], "forgotten": [], "deleted": []}
        now = time.time()
        for job in self.jobs(("queued", "running"), limit=1_000_000):
            self.update_job(
                job.id,
                state="interrupted",
                finished_at=now,
                error="interrupted: the server stopped while the job was " + job.state,
            )
            done["interrupted"].append(job.id)
        for m in self.models(("building", "ready", "deleting")):
            path = data_dir / m.file if m.file else None
            if m.state == "building":
                self.delete_model(m.id)
                done["forgotten"].append(f"{m.id} (its build was interrupted)")
            elif m.state == "deleting":
                if path is not None and m.info.get("owned", True):
                    path.unlink(missing_ok=True)
                self.delete_model(m.id)
                done["deleted"].append(m.id)
            elif path is None or not path.is_file():
                self.delete_model(m.id)
                done["forgotten"].append(f"{m.id} ({m.file}: the file is missing)")
        self.delete_expired_tokens(now)
        return done
