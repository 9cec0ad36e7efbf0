"""Dependencies of the routes, as ``Annotated`` aliases (the FastAPI template's ``deps.py``): the settings and
services the app was built with, and the caller's identity from ``X-API-Key``."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request, Security
from fastapi.security import APIKeyHeader

from core.db import owner_of
from core.settings import Settings
from service.problems import Problem
from service.services import Services


def get_settings_of_app(request: Request) -> Settings:
    """The settings the app was created with (``create_app(settings)``)."""
    return request.app.state.settings  # type: ignore[no-any-return]


def get_services(request: Request) -> Services:
    """The app's services (made in its lifespan)."""
    return request.app.state.services  # type: ignore[no-any-return]


SettingsDep = Annotated[Settings, Depends(get_settings_of_app)]
ServicesDep = Annotated[Services, Depends(get_services)]


# the API-key security scheme (components.securitySchemes.ApiKey): Swagger's Authorize button, and generated clients
# that take the key once; every operation that needs it names it in its ``security``
API_KEY = APIKeyHeader(
    name="X-API-Key",
    scheme_name="ApiKey",
    description="your API key (BONEMESH_API_KEYS); a job, upload or key is seen only with the key that made it",
    auto_error=False,  # a missing key is answered by api_owner: 401 as problem+json
)


def api_owner(settings: SettingsDep, x_api_key: Annotated[str | None, Security(API_KEY)] = None) -> str:
    """The stored owner of the caller's key; 401 unless ``X-API-Key`` is one of the configured keys."""
    ok = False
    for key in settings.api_keys:  # every key compared, in constant time
        ok |= x_api_key is not None and hmac.compare_digest(x_api_key.encode(), key.encode())
    if not ok:
        raise Problem(401, "send a valid API key in the X-API-Key header")
    return owner_of(x_api_key or "")


OwnerDep = Annotated[str, Depends(api_owner)]


def base_url(request: Request, settings: SettingsDep) -> str:
    """The base of the links the API hands out (``BONEMESH_PUBLIC_URL``, else the request's)."""
    return settings.public_url or str(request.base_url)


BaseUrlDep = Annotated[str, Depends(base_url)]
