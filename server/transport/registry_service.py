"""The ModelRegistryService servicer (grpc.aio): RegisterModel, GetModel, ListModels.

Each RPC runs the registry's blocking work (SQL, disk, compiling in a worker process) in a thread,
so the event loop keeps serving other RPCs and session ticks meanwhile.

    model_registry_pb2_grpc.add_ModelRegistryServiceServicer_to_server(
        ModelRegistryServicer(registry), server)
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

import grpc

from jitdyn.errors import InvalidArgument
from jitdyn.registry import DEFAULT_PAGE_SIZE, MAX_PAGE_SIZE, ModelRegistry
from jitdyn.server.estimation.config import Engine
from jitdyn.server.runtime.choice import ModelCosts
from jitdyn.server.transport.auth import tenant_of
from jitdyn.server.transport.model_messages import metadata_from_message, model_message
from jitdyn.server.transport.status import translate_errors
from jitdyn.settings import DEFAULTS
from jitdyn.v1 import model_registry_pb2, model_registry_pb2_grpc

__all__ = ["ModelRegistryServicer"]


class ModelRegistryServicer(model_registry_pb2_grpc.ModelRegistryServiceServicer):
    """Serves `jitdyn.registry` to the tenant of each RPC (server.auth.tenant_of). A model's
    estimator costs are measured when it is registered (a second or so for the largest), or, for
    one registered before costs were measured (the built-in ones too), when it is first shown;
    a listing gives those stored (server/runtime/choice.py)."""

    def __init__(
        self,
        registry: ModelRegistry,
        *,
        engine: Engine = Engine.NATIVE,
        max_tick_share: float = DEFAULTS.max_tick_share,
        max_state_dimension: int = DEFAULTS.max_state_dimension,
        measured: Callable[[], None] | None = None,
    ) -> None:
        self._registry = registry
        self._costs = ModelCosts(
            registry, engine=engine, share=max_tick_share, max_nv=max_state_dimension, measured=measured
        )

    @translate_errors
    async def RegisterModel(
        self,
        request: model_registry_pb2.RegisterModelRequest,
        context: grpc.aio.ServicerContext[
            model_registry_pb2.RegisterModelRequest, model_registry_pb2.RegisterModelResponse
        ],
    ) -> model_registry_pb2.RegisterModelResponse:
        tenant = tenant_of(context)
        metadata = metadata_from_message(request.metadata)
        info, created = await asyncio.to_thread(
            self._registry.register,
            name=request.name,
            mjcf=request.mjcf,
            assets=dict(request.assets),
            metadata=metadata,
            tenant=tenant,
        )
        costs = await asyncio.to_thread(self._costs.table, info)
        return model_registry_pb2.RegisterModelResponse(model=model_message(info, costs), created=created)

    @translate_errors
    async def GetModel(
        self,
        request: model_registry_pb2.GetModelRequest,
        context: grpc.aio.ServicerContext[
            model_registry_pb2.GetModelRequest, model_registry_pb2.GetModelResponse
        ],
    ) -> model_registry_pb2.GetModelResponse:
        tenant = tenant_of(context)
        if request.model_id and (request.name or request.version):
            raise InvalidArgument(
                "GetModelRequest: give model_id, or name (and version), not both; got model_id "
                f"{request.model_id!r}, name {request.name!r}, version {request.version}"
            )
        if not request.model_id and not request.name:
            raise InvalidArgument("GetModelRequest: give model_id, or name (and version); got neither")
        info = await asyncio.to_thread(
            self._registry.get,
            tenant=tenant,
            model_id=request.model_id or None,
            name=request.name or None,
            version=request.version,
        )
        costs = await asyncio.to_thread(self._costs.table, info)
        return model_registry_pb2.GetModelResponse(model=model_message(info, costs))

    @translate_errors
    async def ListModels(
        self,
        request: model_registry_pb2.ListModelsRequest,
        context: grpc.aio.ServicerContext[
            model_registry_pb2.ListModelsRequest, model_registry_pb2.ListModelsResponse
        ],
    ) -> model_registry_pb2.ListModelsResponse:
        tenant = tenant_of(context)
        page_size = request.page_size or DEFAULT_PAGE_SIZE
        if page_size > MAX_PAGE_SIZE:
            raise InvalidArgument(
                f"page_size must be at most {MAX_PAGE_SIZE} (0: {DEFAULT_PAGE_SIZE}), got {page_size}"
            )
        infos, next_page_token = await asyncio.to_thread(
            self._registry.list,
            tenant=tenant,
            name=request.name or None,
            tag=request.tag or None,
            page_size=page_size,
            page_token=request.page_token,
        )
        tables = await asyncio.to_thread(self._costs.stored, infos)
        return model_registry_pb2.ListModelsResponse(
            models=[model_message(info, tables.get(info.id)) for info in infos],
            next_page_token=next_page_token,
        )
