"""The farm's web page, served by the master beside its job API (same aiohttp application, same bind
address): jobs, one job's image assembling live with its partition and the rules' decisions, agents, a
finished job's report. Plain HTML, CSS and JavaScript shipped as package data (`master/web/static`): no
build step and no framework. Live updates by server-sent events; the admin token opens a session.

`routes` mounts it (`add_web_routes`), `auth` keeps sessions and CSRF tokens, `views` reads what is shown,
`events` streams changes, `preview` composes the image so far, `rules` says which rules fired for a unit.
"""

from master.web.routes import add_web_routes

__all__ = ["add_web_routes"]
