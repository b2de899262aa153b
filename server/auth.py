"""Access control: API keys for everything that changes state, viewing tokens for
renders and streams.

- A key is configured (`--api-key`, VASTRAY_API_KEYS) or, with none, made at random at
  start and printed in the URL to open, as Jupyter does: there is never a default secret.
- A viewing token is `vt_<id>_<secret>`: the registry keeps the id, the SHA-256 of the
  secret, what it grants (a model, or a review) and when it expires. The secret is
  compared in constant time.
- Credentials come as `Authorization: Bearer …`, `X-API-Key: …`, or `?key=` / `?token=`
  in the URL (browsers cannot set headers on EventSource and WebSocket).
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import time
from dataclasses import dataclass

from starlette.requests import HTTPConnection

from vastray.server.errors import ApiError
from vastray.server.registry import Registry, TokenRow

TOKEN_PREFIX = "vt"


def credential(conn: HTTPConnection) -> str | None:
    header = conn.headers.get("authorization")
    if header:
        scheme, _, value = header.partition(" ")
        if scheme.lower() == "bearer" and value.strip():
            return value.strip()
    for name in ("x-api-key",):
        if conn.headers.get(name):
            return conn.headers[name].strip()
    for name in ("key", "token"):
        if conn.query_params.get(name):
            return conn.query_params[name].strip()
    return None


def _digest(secret: str) -> str:
    return hashlib.sha256(secret.encode()).hexdigest()


@dataclass(frozen=True)
class Grant:
    """What a credential allows: everything (a key) or one subject (a token)."""

    admin: bool
    scope: str | None = None  # 'model' or 'review'
    subject: str | None = None
    role: str | None = None
    token_id: str | None = None
    model: str | None = None  # the model a viewing or review token shows

    def may_view_model(self, model_id: str) -> bool:
        return self.admin or (self.model is not None and self.model == model_id)


class Auth:
    def __init__(self, keys: list[str], registry: Registry) -> None:
        self.generated = not keys
        self.keys = list(keys) if keys else [secrets.token_urlsafe(24)]
        self.registry = registry

    @property
    def primary_key(self) -> str:
        return self.keys[0]

    def is_key(self, value: str) -> bool:
        # Every key is compared, in constant time, whatever matches first.
        found = False
        for k in self.keys:
            found |= hmac.compare_digest(value.encode(), k.encode())
        return found

    def issue(
        self, scope: str, subject: str, ttl: float, *, label: str | None = None, role: str | None = None
    ) -> tuple[str, TokenRow]:
        token_id, secret = secrets.token_hex(8), secrets.token_urlsafe(24)
        now = time.time()
        row = TokenRow(token_id, _digest(secret), scope, subject, role, label, now, now + ttl)
        self.registry.add_token(row)
        return f"{TOKEN_PREFIX}_{token_id}_{secret}", row

    def grant(self, value: str | None) -> Grant:
        """The grant of a credential; ApiError 401 when it is missing, wrong or expired."""
        if not value:
            raise ApiError(
                401,
                "unauthorized",
                "this endpoint needs an API key or a viewing token "
                "(Authorization: Bearer …, or ?key= / ?token=)",
            )
        if self.is_key(value):
            return Grant(admin=True)
        parts = value.split("_", 2)  # the secret may hold "_" itself
        if len(parts) == 3 and parts[0] == TOKEN_PREFIX:
            row = self.registry.token(parts[1])
            # Compare even when the id is unknown, so timing says nothing about which part is wrong.
            expected = row.secret_hash if row is not None else _digest(secrets.token_urlsafe(24))
            if hmac.compare_digest(_digest(parts[2]), expected) and row is not None:
                if row.expires_at < time.time():
                    raise ApiError(
                        401,
                        "token_expired",
                        f"this token expired at {time.ctime(row.expires_at)}; ask for a new link",
                    )
                model = row.subject
                if row.scope == "review":
                    review = self.registry.review(row.subject)
                    model = review["model_id"] if review is not None else None
                return Grant(
                    admin=False,
                    scope=row.scope,
                    subject=row.subject,
                    role=row.role,
                    token_id=row.id,
                    model=model,
                )
        raise ApiError(401, "unauthorized", "the key or token is not valid")

    def require_key(self, conn: HTTPConnection) -> Grant:
        grant = self.grant(credential(conn))
        if not grant.admin:
            raise ApiError(403, "forbidden", "this endpoint needs an API key; a viewing token only views")
        return grant

    def require_model_view(self, conn: HTTPConnection, model_id: str) -> Grant:
        grant = self.grant(credential(conn))
        if not grant.may_view_model(model_id):
            raise ApiError(403, "forbidden", f"this token does not grant access to model {model_id}")
        return grant
