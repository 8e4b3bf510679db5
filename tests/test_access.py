"""Who may drive the dashboard (`app.api.access`), on real sockets: a page on another origin can neither open the viser
WebSocket nor POST to the API, a DNS-rebinding Host is refused by both servers, and off loopback (or with a
token) every API request and the WebSocket need the token printed at start-up."""

from __future__ import annotations

import browser_support
import httpx
import pytest
import viser
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from app.server import Dashboard
from gsmn.config import preset, with_overrides

pytestmark = pytest.mark.unit

PROTOCOL = [f"viser-v{viser.__version__}"]


def dashboard(tmp_path, **kwargs) -> Dashboard:
    return Dashboard(with_overrides(preset("tiny"), {"task.horizon": "20"}), port=0, api_port=0,
                     checkpoints_root=tmp_path / "none", data_dir=tmp_path / "data", **kwargs)


def ws_url(d: Dashboard) -> str:
    return f"ws://127.0.0.1:{d.viser.get_port()}"


def page_origin(d: Dashboard) -> str:
    return f"http://127.0.0.1:{d.viser.get_port()}"


def ws_status(uri: str, **kwargs) -> int:
    """101 when the handshake is accepted, else the HTTP status it was refused with."""
    try:
        with connect(uri, subprotocols=PROTOCOL, open_timeout=20, **kwargs):
            return 101
    except InvalidStatus as e:
        return e.response.status_code


@pytest.fixture(scope="module")
def loopback(tmp_path_factory):
    d = dashboard(tmp_path_factory.mktemp("loopback"))
    try:
        yield d
    finally:
        d.close()


def test_the_websocket_accepts_only_the_pages_own_origin(loopback):
    assert ws_status(ws_url(loopback), origin=page_origin(loopback)) == 101
    assert ws_status(ws_url(loopback), origin=f"http://localhost:{loopback.viser.get_port()}") == 101
    assert ws_status(ws_url(loopback), origin="http://evil.example") == 403
    assert ws_status(ws_url(loopback), origin="null") == 403
    assert ws_status(ws_url(loopback), origin="http://127.0.0.1:1") == 403  # another port: another origin


def test_a_cross_origin_post_is_refused_and_a_program_s_is_not(loopback):
    api = loopback.urls.api
    evil = httpx.post(f"{api}/api/evaluations/2/resume", content=b"x",
                      headers={"Origin": "http://evil.example", "Content-Type": "text/plain"})
    assert evil.status_code == 403 and "origin" in evil.json()["detail"]
    # the same request from a program (no Origin) or from the API's own /docs page reaches the route
    assert httpx.post(f"{api}/api/evaluations/2/resume", content=b"x").status_code == 404
    assert httpx.post(f"{api}/api/evaluations/2/resume", headers={"Origin": api}).status_code == 404
    # reading is not state-changing: a GET with a foreign Origin is answered (the browser keeps it from the page)
    assert httpx.get(f"{api}/api/health", headers={"Origin": "http://evil.example"}).status_code == 200


def test_a_wrong_host_is_refused_by_both_servers(loopback):
    """DNS rebinding: the attacker's name resolves to 127.0.0.1, its requests carry it as Host."""
    bad = httpx.get(f"{loopback.urls.api}/api/health", headers={"Host": "attacker.example"})
    assert bad.status_code == 421 and "attacker.example" in bad.json()["detail"]
    assert httpx.get(loopback.urls.page, headers={"Host": "attacker.example"}).status_code == 421
    assert ws_status(ws_url(loopback), additional_headers={"Host": "attacker.example:1"}) == 421
    assert httpx.get(f"{loopback.urls.api}/api/health").status_code == 200
    assert httpx.get(loopback.urls.page).status_code == 200
    assert loopback.urls.token is None and loopback.urls.notes == ()


def test_off_loopback_a_token_is_needed_and_a_wrong_one_refused(tmp_path):
    d = dashboard(tmp_path, host="0.0.0.0")
    try:
        token = d.urls.token
        assert token and len(token) >= 20
        assert d.urls.page.endswith(f"/?token={token}")
        assert any(n.startswith("warning: bound to 0.0.0.0") for n in d.urls.notes)
        assert any("http://127.0.0.1:" in n for n in d.urls.notes)  # the addresses it really answers on
        api = d.urls.api
        missing = httpx.get(f"{api}/api/health")
        assert missing.status_code == 401 and "token" in missing.json()["detail"]
        assert httpx.get(f"{api}/api/health", headers={"Authorization": "Bearer wrong"}).status_code == 403
        assert httpx.get(f"{api}/api/health", headers={"Authorization": f"Bearer {token}"}).status_code == 200
        assert httpx.get(f"{api}/api/health", headers={"X-GSMN-Token": token}).status_code == 200
        # the page's WebSocket: refused without, with a wrong one; the page URL's ?token= sets the cookie it carries
        assert ws_status(ws_url(d), origin=page_origin(d)) == 401
        assert ws_status(ws_url(d) + "/?token=wrong", origin=page_origin(d)) == 403
        page = httpx.get(d.urls.page)
        assert page.status_code == 200
        cookie = page.headers["set-cookie"]
        assert cookie.startswith(f"gsmn_token_{d.viser.get_port()}={token}") and "HttpOnly" in cookie
        assert ws_status(ws_url(d), origin=page_origin(d), additional_headers={"Cookie": cookie.split(";")[0]}) == 101
        # the same cookie goes to the API (cookies are per host, not per port)
        assert httpx.get(f"{api}/api/health", headers={"Cookie": cookie.split(";")[0]}).status_code == 200
        # a right token from a foreign origin is still refused
        assert ws_status(ws_url(d) + f"/?token={token}", origin="http://evil.example") == 403
    finally:
        d.close()


def test_a_token_given_on_loopback_is_required_too(tmp_path):
    d = dashboard(tmp_path, token="s3cret-token")
    try:
        assert d.urls.token == "s3cret-token" and "token: s3cret-token" in d.urls.notes[-1]
        assert httpx.get(f"{d.urls.api}/api/health").status_code == 401
        assert httpx.get(f"{d.urls.api}/api/health?token=s3cret-token").status_code == 200
        assert ws_status(ws_url(d) + "/?token=s3cret-token", origin=page_origin(d)) == 101
    finally:
        d.close()


@pytest.mark.browser
def test_the_page_carries_its_token_to_its_websocket_in_a_browser(tmp_path):
    """Headless Chromium: the printed URL (with ?token=) gives a working page, whose WebSocket carries the cookie
    that URL set; the bare URL gets the page's HTML but no connection, so no controls."""
    d = dashboard(tmp_path, token="")
    try:
        assert "?token=" in d.urls.page
        with browser_support.chromium() as browser:
            page = browser.new_page()
            page.set_default_timeout(60_000)
            page.goto(d.urls.page)
            page.get_by_role("button", name="Run", exact=True).wait_for()  # the GUI came over the WebSocket
            bare = browser.new_context().new_page()  # no cookie
            bare.goto(page_origin(d))
            opens = """([url, protocol]) => new Promise(done => {
                const ws = new WebSocket(url, [protocol]);
                ws.onopen = () => { ws.close(); done(true); };
                ws.onerror = () => done(false);
            })"""
            assert page.evaluate(opens, [ws_url(d), PROTOCOL[0]]) is True
            assert bare.evaluate(opens, [ws_url(d), PROTOCOL[0]]) is False
            assert bare.get_by_role("button", name="Run", exact=True).count() == 0
    finally:
        d.close()
