"""The model registry: MuJoCo models registered by clients, addressed by content, versioned by name.

    with ModelRegistry(engine=open_index(url), data_root=Path("jitdyn-data")) as registry:
        registry.register_builtins()
        info, created = registry.register(name="arm", mjcf=xml, assets={"arm.stl": data},
                                          metadata=ModelMetadata(tags=("lab",)))
        model = registry.load(info.id)

The index row of a model lives in the SQL table `models` (storage.schema); its MJCF and assets in a
zip in the index's `model_blobs` table, cached under <data root>/models/ (registry.store), so that
every server sharing the index opens every model. A tenant sees its own models and the built-in ones,
which belong to the default tenant "" and whose names nobody else may register under.
"""

from __future__ import annotations

import base64
import binascii
import copy
import dataclasses
import datetime
import hashlib
import json
import logging
import threading
from collections import OrderedDict
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import mujoco
import sqlalchemy as sa

from jitdyn.errors import FailedPrecondition, InvalidArgument, NotFound, Unavailable
from jitdyn.lifecycle import Closeable
from jitdyn.registry.builtins import builtin_models
from jitdyn.registry.compile import ModelCompiler, check_request
from jitdyn.registry.content_id import check_content_id, content_id
from jitdyn.registry.costs import CandidateCost, read_costs, store_costs
from jitdyn.registry.info import (
    ActuatorInfo,
    JointInfo,
    ModelInfo,
    ModelMetadata,
    ModelShape,
    check_metadata,
    check_name,
    check_tag,
    describe_model,
    stored_defaults,
)
from jitdyn.registry.limits import DEFAULT_LIMITS, RegistryLimits
from jitdyn.registry.store import fetch_blob, publish_blob, read_blob, write_blob
from jitdyn.roles import joint_roles
from jitdyn.storage.schema import models

__all__ = ["DEFAULT_PAGE_SIZE", "MAX_PAGE_SIZE", "ModelRegistry"]

_log = logging.getLogger(__name__)

DEFAULT_PAGE_SIZE = 50
MAX_PAGE_SIZE = 1000
# Concurrent registrations of one name race for its next version; the loser re-reads and retries.
_INSERT_ATTEMPTS = 20
_LISTED_NAMES = 12
_LISTED_VERSIONS = 20
_BUILTIN_TENANT = ""
_NO_METADATA = ModelMetadata()


def _check_tenant(tenant: object) -> str:
    if not isinstance(tenant, str) or len(tenant) > 64:
        raise InvalidArgument(f"tenant must be a string of at most 64 characters, got {tenant!r}")
    return tenant


def _utc(value: datetime.datetime) -> datetime.datetime:
    # SQLite hands back naive datetimes; every stored time is UTC.
    if value.tzinfo is None:
        return value.replace(tzinfo=datetime.UTC)
    return value.astimezone(datetime.UTC)


class _ModelCache:
    """Compiled models by id, at most `capacity` bytes of them (mj_sizeModel), the least recently
    used dropped first. Not thread-safe: the registry holds its lock around every call."""

    def __init__(self, capacity: int) -> None:
        self._capacity = capacity
        self._models: OrderedDict[str, tuple[mujoco.MjModel, int]] = OrderedDict()
        self.bytes = 0

    def get(self, model_id: str) -> mujoco.MjModel | None:
        entry = self._models.get(model_id)
        if entry is None:
            return None
        self._models.move_to_end(model_id)
        return entry[0]

    def put(self, model_id: str, model: mujoco.MjModel) -> None:
        size = int(mujoco.mj_sizeModel(model))
        if model_id in self._models or size > self._capacity:
            return
        self._models[model_id] = (model, size)
        self.bytes += size
        while self.bytes > self._capacity:
            _, (_, dropped) = self._models.popitem(last=False)
            self.bytes -= dropped

    def clear(self) -> None:
        self._models.clear()
        self.bytes = 0


class ModelRegistry(Closeable):
    """Registers, finds and loads models; thread-safe. A context manager; `close()` is safe twice.

    Args:
      engine: the SQL index, migrated (storage.db.open_index). The registry does not dispose it.
      data_root: the data folder; models are stored under its models/ folder.
      limits: what a registered model may be (registry.limits).
      compile_workers: how many models may compile at once, each in its own process.
    """

    def __init__(
        self,
        *,
        engine: sa.Engine,
        data_root: Path,
        limits: RegistryLimits = DEFAULT_LIMITS,
        compile_workers: int = 1,
    ) -> None:
        if not isinstance(limits, RegistryLimits):
            raise TypeError(f"limits must be a RegistryLimits, got {type(limits).__name__}")
        self._engine = engine
        self._data_root = Path(data_root)
        self._limits = limits
        self._compiler = ModelCompiler(limits=limits, workers=compile_workers)
        self._cache = _ModelCache(limits.cache_bytes)
        self._cache_lock = threading.Lock()
        self._load_locks: dict[str, threading.Lock] = {}
        self._closed = False

    @property
    def limits(self) -> RegistryLimits:
        return self._limits

    @property
    def data_root(self) -> Path:
        return self._data_root

    # -- lifecycle ------------------------------------------------------------------------------

    def close(self) -> None:
        """Stop the compile workers and drop the cache; safe to call twice."""
        self._closed = True
        self._compiler.close()
        with self._cache_lock:
            self._cache.clear()

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("the ModelRegistry is closed")

    # -- rows -------------------------------------------------------------------------------------

    @staticmethod
    def _visible(tenant: str) -> sa.ColumnElement[bool]:
        """Rows `tenant` may see: its own and the built-in models."""
        own = models.c.tenant == tenant
        if tenant == _BUILTIN_TENANT:
            return own
        return sa.or_(own, sa.and_(models.c.builtin == sa.true(), models.c.tenant == _BUILTIN_TENANT))

    def _names_listed(self, tenant: str) -> str:
        """'the registered models are a, b, ... (12 in all)': the names `tenant` sees, for a
        message about a name that is not one of them."""
        with self._engine.connect() as connection:
            names = list(
                connection.execute(
                    sa.select(models.c.name).where(self._visible(tenant)).distinct().order_by(models.c.name)
                ).scalars()
            )
        if not names:
            return "no model is registered"
        shown = ", ".join(names[:_LISTED_NAMES])
        more = f", ... ({len(names)} in all: jitdyn models list)" if len(names) > _LISTED_NAMES else ""
        return f"the registered models are {shown}{more}"

    @staticmethod
    def _info(row: sa.Row[Any]) -> ModelInfo:
        described = json.loads(row.description_json)
        return ModelInfo(
            id=row.id,
            name=row.name,
            version=int(row.version),
            tenant=row.tenant,
            builtin=bool(row.builtin),
            nq=int(row.nq),
            nv=int(row.nv),
            nu=int(row.nu),
            na=int(row.na),
            nsensor=int(row.nsensor),
            nbody=int(row.nbody),
            timestep=float(row.timestep),
            joints=tuple(JointInfo(**joint) for joint in described["joints"]),
            actuators=tuple(ActuatorInfo(**actuator) for actuator in described["actuators"]),
            description=described["description"],
            tags=tuple(row.tags.split()),
            defaults=stored_defaults(described["defaults"]),
            created_at=_utc(row.created_at),
        )

    def _find_id(self, connection: sa.Connection, tenant: str, model_id: str) -> ModelInfo | None:
        rows = connection.execute(
            sa.select(models).where(models.c.id == model_id, self._visible(tenant))
        ).all()
        if not rows:
            return None
        # A tenant's own row first: it may have registered the content before it became built-in.
        return self._info(min(rows, key=lambda row: row.tenant != tenant))

    # -- register ---------------------------------------------------------------------------------

    def register(
        self,
        *,
        name: str,
        mjcf: str,
        assets: Mapping[str, bytes],
        metadata: ModelMetadata = _NO_METADATA,
        tenant: str = "",
        builtin: bool = False,
    ) -> tuple[ModelInfo, bool]:
        """Compile and store a model; return it and whether it is new.

        Content identical to a model `tenant` can see returns that model (`created` False), whatever
        its name. Otherwise the model becomes the next version of `name` in `tenant`.

        Raises:
          InvalidArgument: a bad name, metadata, MJCF or asset (registry.compile), or the name of a
            built-in model.
          ResourceExhausted: over a limit of `limits`.
        """
        self._check_open()
        name = check_name(name)
        tenant = _check_tenant(tenant)
        metadata = check_metadata(metadata)
        if builtin and tenant != _BUILTIN_TENANT:
            raise InvalidArgument(f"built-in models belong to the default tenant '', got tenant {tenant!r}")
        check_request(mjcf, assets, limits=self._limits)
        model_id = content_id(mjcf, assets)
        with self._engine.connect() as connection:
            existing = self._find_id(connection, tenant, model_id)
            if existing is not None:
                return existing, False
            if not builtin:
                self._check_not_builtin_name(connection, name)
                self._check_quota(connection, tenant, mjcf, assets)
        model = self._compiler.compile(mjcf, assets)
        shape = describe_model(model)
        joint_roles(shape.joints, metadata.tags)  # a role tag naming no joint or no role is refused
        blob = write_blob(self._data_root, model_id, mjcf, assets, engine=self._engine)
        size = len(mjcf.encode("utf-8")) + sum(len(data) for data in assets.values())
        with self._cache_lock:
            self._cache.put(model_id, model)
        for _ in range(_INSERT_ATTEMPTS):
            try:
                with self._engine.begin() as connection:
                    existing = self._find_id(connection, tenant, model_id)
                    if existing is not None:
                        return existing, False
                    latest = connection.execute(
                        sa.select(sa.func.max(models.c.version)).where(
                            models.c.tenant == tenant, models.c.name == name
                        )
                    ).scalar_one()
                    values = self._row(
                        model_id=model_id,
                        name=name,
                        version=(latest or 0) + 1,
                        tenant=tenant,
                        builtin=builtin,
                        shape=shape,
                        metadata=self._with_earlier_tags(connection, tenant, name, latest, metadata),
                        blob=blob,
                        size=size,
                    )
                    connection.execute(sa.insert(models).values(**values))
                    row = connection.execute(
                        sa.select(models).where(models.c.tenant == tenant, models.c.id == model_id)
                    ).one()
                    return self._info(row), True
            except sa.exc.IntegrityError:
                continue  # another registration took this id or version first: re-read
        raise RuntimeError(
            f"could not register model {name!r}: {_INSERT_ATTEMPTS} concurrent registrations won the race first"
        )

    def _with_earlier_tags(
        self, connection: sa.Connection, tenant: str, name: str, latest: int | None, metadata: ModelMetadata
    ) -> ModelMetadata:
        """`metadata`, with the tags of version `latest` of `name` when it gives none: a new
        version of a model is still what its tags said (registering with tags replaces them)."""
        if not latest or metadata.tags:
            return metadata
        tags = connection.execute(
            sa.select(models.c.tags).where(
                models.c.tenant == tenant, models.c.name == name, models.c.version == latest
            )
        ).scalar_one()
        return dataclasses.replace(metadata, tags=tuple(tags.split()))

    def _check_quota(
        self, connection: sa.Connection, tenant: str, mjcf: str, assets: Mapping[str, bytes]
    ) -> None:
        """Refuse a model over the tenant's model count or stored bytes (ResourceExhausted)."""
        count, stored = connection.execute(
            sa.select(sa.func.count(), sa.func.coalesce(sa.func.sum(models.c.size_bytes), 0)).where(
                models.c.tenant == tenant, models.c.builtin == sa.false()
            )
        ).one()
        self._limits.check(
            "max_models_per_tenant", "the number of this tenant's models, with this one", count + 1
        )
        size = len(mjcf.encode("utf-8")) + sum(len(data) for data in assets.values())
        self._limits.check(
            "max_tenant_bytes",
            "the bytes this tenant's models store, with this one",
            int(stored) + size,
            " bytes",
        )

    def _check_not_builtin_name(self, connection: sa.Connection, name: str) -> None:
        taken = connection.execute(
            sa.select(models.c.pk)
            .where(models.c.name == name, models.c.builtin == sa.true(), models.c.tenant == _BUILTIN_TENANT)
            .limit(1)
        ).first()
        if taken is not None:
            raise InvalidArgument(f"name {name!r} belongs to a built-in model; register under another name")

    @staticmethod
    def _row(
        *,
        model_id: str,
        name: str,
        version: int,
        tenant: str,
        builtin: bool,
        shape: ModelShape,
        metadata: ModelMetadata,
        blob: str,
        size: int,
    ) -> dict[str, Any]:
        described = {
            "description": metadata.description,
            "defaults": metadata.defaults,
            "joints": [dataclasses.asdict(joint) for joint in shape.joints],
            "actuators": [dataclasses.asdict(actuator) for actuator in shape.actuators],
        }
        return {
            "tenant": tenant,
            "id": model_id,
            "name": name,
            "version": version,
            "builtin": builtin,
            "nq": shape.nq,
            "nv": shape.nv,
            "nu": shape.nu,
            "na": shape.na,
            "nsensor": shape.nsensor,
            "nbody": shape.nbody,
            "timestep": shape.timestep,
            "description_json": json.dumps(described, sort_keys=True),
            "tags": " ".join(metadata.tags),
            "blob_path": blob,
            "size_bytes": size,
            "created_at": datetime.datetime.now(datetime.UTC),
        }

    def register_builtins(self) -> list[ModelInfo]:
        """Register the built-in models of models/ (idempotent: unchanged ones are returned as stored)."""
        infos = []
        for builtin in builtin_models():
            info, _ = self.register(
                name=builtin.name,
                mjcf=builtin.mjcf,
                assets={},
                metadata=ModelMetadata(description=builtin.description, tags=builtin.tags),
                tenant=_BUILTIN_TENANT,
                builtin=True,
            )
            infos.append(info)
        return infos

    # -- get and list -----------------------------------------------------------------------------

    def get(
        self, *, tenant: str = "", model_id: str | None = None, name: str | None = None, version: int = 0
    ) -> ModelInfo:
        """One model, by content id or by name and version (0: the newest).

        Raises:
          InvalidArgument: both or neither of `model_id` and `name`, or a malformed one.
          NotFound: no such model visible to `tenant`.
        """
        self._check_open()
        tenant = _check_tenant(tenant)
        if isinstance(version, bool) or not isinstance(version, int) or version < 0:
            raise InvalidArgument(f"version must be a non-negative integer (0: the newest), got {version!r}")
        if model_id and name:
            raise InvalidArgument(
                f"give model_id or name, not both; got model_id {model_id!r} and name {name!r}"
            )
        if model_id:
            if version:
                raise InvalidArgument(f"version applies to a name, not to model_id; got version {version}")
            check_content_id(model_id)
            with self._engine.connect() as connection:
                info = self._find_id(connection, tenant, model_id)
            if info is None:
                raise NotFound(f"no model has id {model_id!r}")
            return info
        if not name:
            raise InvalidArgument("give model_id or name; got neither")
        check_name(name)
        with self._engine.connect() as connection:
            rows = connection.execute(
                sa.select(models)
                .where(models.c.name == name, self._visible(tenant))
                .order_by(models.c.version.desc())
            ).all()
        if not rows:
            raise NotFound(f"no model is named {name!r}; {self._names_listed(tenant)}")
        if version == 0:
            return self._info(rows[0])
        for row in rows:
            if row.version == version:
                return self._info(row)
        versions = sorted(int(row.version) for row in rows)
        shown = ", ".join(str(v) for v in versions[:_LISTED_VERSIONS])
        more = f", ... ({len(versions)} in all)" if len(versions) > _LISTED_VERSIONS else ""
        raise NotFound(f"model {name!r} has no version {version} (versions: {shown}{more})")

    def list(
        self,
        *,
        tenant: str = "",
        name: str | None = None,
        tag: str | None = None,
        page_size: int = DEFAULT_PAGE_SIZE,
        page_token: str = "",
    ) -> tuple[list[ModelInfo], str]:
        """A page of the models `tenant` sees, by name, then newest version first; and the token of
        the next page ("" on the last).

        Raises:
          InvalidArgument: a bad filter, page size (1-1000) or a token not from the same listing.
        """
        self._check_open()
        tenant = _check_tenant(tenant)
        if name:
            check_name(name, argument="name filter")
        if tag:
            check_tag(tag, argument="tag filter")
        if (
            isinstance(page_size, bool)
            or not isinstance(page_size, int)
            or not 1 <= page_size <= MAX_PAGE_SIZE
        ):
            raise InvalidArgument(f"page_size must be between 1 and {MAX_PAGE_SIZE}, got {page_size!r}")
        filters = _fingerprint(tenant, name or "", tag or "")
        query = sa.select(models).where(self._visible(tenant))
        if name:
            query = query.where(models.c.name == name)
        if tag:
            query = query.where(self._has_tag(tag))
        if page_token:
            after_name, after_version = _decode_token(page_token, filters)
            query = query.where(
                sa.or_(
                    models.c.name > after_name,
                    sa.and_(models.c.name == after_name, models.c.version < after_version),
                )
            )
        query = query.order_by(models.c.name, models.c.version.desc()).limit(page_size + 1)
        with self._engine.connect() as connection:
            rows = connection.execute(query).all()
        page = [self._info(row) for row in rows[:page_size]]
        token = ""
        if len(rows) > page_size:
            token = _encode_token(page[-1].name, page[-1].version, filters)
        return page, token

    def _has_tag(self, tag: str) -> sa.ColumnElement[bool]:
        padded = sa.literal(" ") + models.c.tags + sa.literal(" ")
        if self._engine.dialect.name == "sqlite":
            # SQLite's LIKE ignores case; GLOB does not, and tags hold none of its wildcards.
            return padded.op("GLOB")(f"* {tag} *")
        return padded.contains(f" {tag} ", autoescape=True)

    # -- estimator costs ----------------------------------------------------------------------

    def costs(self, model_ids: Iterable[str]) -> dict[str, tuple[CandidateCost, ...]]:
        """The stored estimator costs of those of `model_ids` that were measured (registry.costs)."""
        self._check_open()
        return read_costs(self._engine, model_ids)

    def store_costs(self, model_id: str, costs: Sequence[CandidateCost]) -> tuple[CandidateCost, ...]:
        """Store the measured estimator costs of `model_id` unless stored already; the stored ones."""
        self._check_open()
        check_content_id(model_id)
        return store_costs(self._engine, model_id, costs)

    # -- load -------------------------------------------------------------------------------------

    def load(self, model_id: str, *, tenant: str = "") -> mujoco.MjModel:
        """The compiled model of `model_id`: a copy of the registry's cached one, to use as you like.

        Raises:
          InvalidArgument: a malformed id.
          NotFound: no such model visible to `tenant`.
        """
        self._check_open()
        tenant = _check_tenant(tenant)
        check_content_id(model_id)
        try:
            with self._engine.connect() as connection:
                row = connection.execute(
                    sa.select(models.c.blob_path)
                    .where(models.c.id == model_id, self._visible(tenant))
                    .limit(1)
                ).first()
        except sa.exc.SQLAlchemyError as error:
            raise _index_unreachable(model_id, error) from None
        if row is None:
            raise NotFound(f"no model has id {model_id!r}")
        with self._cache_lock:
            model = self._cache.get(model_id)
            lock = self._load_locks.setdefault(model_id, threading.Lock())
        if model is None:
            with lock:  # one compile per id, however many sessions open it at once
                with self._cache_lock:
                    model = self._cache.get(model_id)
                if model is None:
                    mjcf, assets = self._content(model_id, row.blob_path)
                    stored = content_id(mjcf, assets)
                    if stored != model_id:
                        raise RuntimeError(
                            f"stored model {row.blob_path} has content id {stored}, not {model_id}"
                        )
                    model = self._compiler.compile(mjcf, assets)
                    with self._cache_lock:
                        self._cache.put(model_id, model)
        return copy.copy(model)

    def _content(self, model_id: str, relative: str) -> tuple[str, dict[str, bytes]]:
        """The MJCF and assets of `model_id`: from this server's data folder, else fetched from the
        index into it (a model registered through another server sharing the index)."""
        try:
            content = read_blob(self._data_root, relative)
        except FileNotFoundError:
            pass
        else:
            self._backfill(model_id, relative)
            return content
        try:
            fetched = fetch_blob(self._engine, self._data_root, model_id)
        except sa.exc.SQLAlchemyError as error:
            raise _index_unreachable(model_id, error) from None
        if fetched is None:
            # Registered before the index held model content, through a server whose data folder
            # this one does not share: a deployment fault to name, never a server path to leak.
            _log.error(
                "model %s: %s is missing under %s and from the index", model_id, relative, self._data_root
            )
            raise FailedPrecondition(
                f"model {model_id} is registered in the index but its MJCF and assets are neither in "
                "the index nor in this server's data folder; register it again through the server "
                "that holds them"
            )
        return read_blob(self._data_root, fetched)

    def _backfill(self, model_id: str, relative: str) -> None:
        """Put a locally stored model's content into the index when it is not there yet: models
        registered before the index held content (migration 0002) reach the other servers once
        a server holding them loads them. Best effort: the local copy serves this server anyway."""
        try:
            publish_blob(self._engine, model_id, (self._data_root / relative).read_bytes())
        except (OSError, sa.exc.SQLAlchemyError) as error:
            _log.warning("model %s: could not copy its content into the index: %s", model_id, error)


def _index_unreachable(model_id: str, error: BaseException) -> Unavailable:
    """The client's reason when the index that holds a model's content cannot be read; the server
    log keeps the database's own message, which may name hosts and files."""
    _log.error("model %s: reading the index failed: %s: %s", model_id, type(error).__name__, error)
    return Unavailable(
        f"model {model_id} cannot be loaded: the shared index that holds models and their MJCF and "
        f"assets cannot be reached ({type(error).__name__}); try again later"
    )


def _fingerprint(tenant: str, name: str, tag: str) -> str:
    return hashlib.sha256(json.dumps([tenant, name, tag]).encode("utf-8")).hexdigest()[:16]


def _encode_token(name: str, version: int, filters: str) -> str:
    payload = json.dumps({"after": [name, version], "filters": filters}, separators=(",", ":"))
    return base64.urlsafe_b64encode(payload.encode("utf-8")).decode("ascii").rstrip("=")


def _decode_token(token: str, filters: str) -> tuple[str, int]:
    bad = InvalidArgument(
        f"page_token {token[:80]!r} is not a next_page_token of this listing (same filters)"
    )
    if not isinstance(token, str) or len(token) > 512:
        raise bad
    try:
        payload = json.loads(base64.urlsafe_b64decode(token + "=" * (-len(token) % 4)))
        after_name, after_version = payload["after"]
        token_filters = payload["filters"]
    except (binascii.Error, UnicodeDecodeError, ValueError, KeyError, TypeError):
        raise bad from None
    if (
        token_filters != filters
        or not isinstance(after_name, str)
        or isinstance(after_version, bool)
        or not isinstance(after_version, int)
    ):
        raise bad
    return after_name, after_version
