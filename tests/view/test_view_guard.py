"""The view's guard in front of every route (sssphase_view.app.Guard), driven as ASGI: the Host a loopback view
answers to (IPv4 and IPv6), a websocket from a page of another origin, and nosniff on the framework's own answers."""

from __future__ import annotations

import asyncio

import pytest

pytest.importorskip("starlette")

from sssphase_view.app import Guard  # noqa: E402


def _call(hosts: list[str] | None, kind: str, host: str | None, origin: str | None = None) -> tuple[bool, list[dict]]:
    """(whether the app behind a guard of ``hosts`` was reached, what was sent)."""
    reached, sent = [], []

    async def app(scope, receive, send):  # noqa: ANN001, ANN202
        reached.append(scope)
        if kind == "http":
            await send({"type": "http.response.start", "status": 404, "headers": [(b"content-type", b"text/plain")]})
            await send({"type": "http.response.body", "body": b"Not Found"})

    async def receive():  # noqa: ANN202
        return {"type": "http.request", "body": b""}

    async def send(message):  # noqa: ANN001, ANN202
        sent.append(message)

    headers = [(b"host", host.encode())] if host is not None else []
    headers += [(b"origin", origin.encode())] if origin is not None else []
    scope = {"type": kind, "path": "/", "headers": headers, "method": "GET", "query_string": b"", "root_path": "",
             "scheme": "ws" if kind == "websocket" else "http", "server": ("127.0.0.1", 80), "http_version": "1.1"}
    asyncio.run(Guard(app, hosts=hosts)(scope, receive, send))
    return bool(reached), sent


def test_a_loopback_view_answers_its_own_names_only_ipv6_too():
    """On ::1 no Host was checked at all (Starlette's check cannot parse an IPv6 Host): DNS rebinding reached it."""
    hosts = ["::1", "127.0.0.1", "localhost"]
    for host in ("[::1]:8000", "[::1]", "127.0.0.1:8000", "localhost:8000", "LOCALHOST"):
        assert _call(hosts, "http", host)[0], host
    for host in ("evil.example", "evil.example:8000", "[::2]:8000", "127.0.0.1.", "", "[::1", None):
        reached, sent = _call(hosts, "http", host)
        assert not reached and sent[0]["status"] == 400, host
        assert (b"x-content-type-options", b"nosniff") in sent[0]["headers"]
    assert _call(None, "http", "evil.example")[0]  # --allow-remote: the token alone guards


def test_a_websocket_from_a_page_of_another_origin_is_refused_and_every_answer_says_nosniff():
    hosts = ["127.0.0.1", "localhost"]
    assert _call(hosts, "websocket", "127.0.0.1:8000", "http://127.0.0.1:8000")[0]
    assert _call(hosts, "websocket", "127.0.0.1:8000")[0]  # no Origin: not a browser page
    for origin in ("http://evil.example", "http://127.0.0.1:9999", "http://localhost:8000", "http://[::1"):
        reached, sent = _call(hosts, "websocket", "127.0.0.1:8000", origin)
        assert not reached and sent == [{"type": "websocket.close", "code": 1008}], origin
    assert not _call(hosts, "websocket", "evil.example:8000", "http://evil.example:8000")[0]  # rebinding, same origin
    reached, sent = _call(hosts, "http", "127.0.0.1:8000")  # the framework's own 404
    assert reached and (b"x-content-type-options", b"nosniff") in sent[0]["headers"]


def test_live_settings_take_only_values_of_their_type_and_range():
    """``{"decode": "no"}`` turned live decode on (any non-empty string is true); ``true`` as an exposure or a
    frame number was taken as 1."""
    from sssphase_view.app import apply_live_message
    from sssphase_view.live import LiveSettings

    settings = LiveSettings()
    for garbage in ({"decode": "no"}, {"decode": 1}, {"exposure": True}, {"exposure": 1e9}, {"psp_frame": True},
                    {"pattern": "../etc"}, {"gain": "high"}, {"gain": -1}):
        apply_live_message(settings, garbage)
    assert settings == LiveSettings()
    apply_live_message(settings, {"decode": True, "exposure": 2, "psp_frame": 3, "pattern": "psp", "gain": 0.5})
    assert (settings.decode, settings.exposure, settings.psp_frame, settings.pattern, settings.gain) == (True, 2.0, 3, "psp", 0.5)
    apply_live_message(settings, {"decode": False, "gain": None})
    assert settings.decode is False and settings.gain is None
