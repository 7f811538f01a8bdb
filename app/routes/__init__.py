"""One module per resource; ``V1_ROUTERS`` are the authenticated API, ``health`` is open."""

from app.routes import capacity, detect, embed, health, jobs, preview, tracing

V1_ROUTERS = (embed.router, detect.router, capacity.router, preview.router, tracing.router, jobs.router)

__all__ = ["V1_ROUTERS", "health"]
