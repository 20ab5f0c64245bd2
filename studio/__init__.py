"""Impulse Studio (`impulse studio`): a local browser app to browse, edit and play levels on our own engine.

An ASGI server (`studio.app.make_app`, Starlette, served by uvicorn) and static front-end files (`studio/static`,
plain JavaScript, no build step). The server does everything that needs the engine: it lists and draws level sets
(`studio.library`), edits and validates levels (`studio.editing`, `studio.level_io`) and steps one jitted environment
per connection for play (`studio.play`); the browser only draws the scene geometry it is sent and turns the user's
mouse and keys into requests. docs/studio.md describes the pages and the WebSocket protocol.
"""
