"""Issue 13: blinding through headers and hostile input (each test failed before its fix)."""

import csv
import hashlib
import http.client
import io
import json
import os
import re

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.exc import OperationalError

from server.app import create_app
from server.config import Settings
from server.deps import get_session
from server.errors import Conflict
from server.pages import STATIC_DIR
from server.participants import service
from server.researchers.service import create_researcher
from server.security import LoginLimiter, RateLimiter
from tests.server_fixtures import RESEARCHER, answer_all, live_server, start, vote

SECURITY = ("content-security-policy", "x-content-type-options", "x-frame-options", "referrer-policy")
NAME = re.compile(r"[0-9a-f]{24}\.(mp4|jpg)")


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def client_from(app, address: str) -> TestClient:
    return TestClient(app, client=(address, 50000))


def normalized(headers) -> dict:
    """Headers without the date, with media names replaced by NAME (the ETag is legitimately the name)."""
    return {k: NAME.sub("NAME", v) for k, v in headers.items() if k != "date"}


# --- 1: nothing a participant fetches depends on when or in what order files were written ---------------------

def test_header_audit_media_pages_static_and_api_do_not_depend_on_write_order(client, study):
    media = client.app.state.settings.media_dir
    media.mkdir(parents=True, exist_ok=True)
    sid, headers = start(client)
    trials = answer_all(client, sid, headers)
    urls = list(dict.fromkeys(t["video_url"] for t in trials))
    names = [u.rsplit("/", 1)[1] for u in urls]
    names += [n.replace(".mp4", ".jpg") for n in names]  # posters
    for i, name in enumerate(names):  # same size, written in order, hours apart
        (media / name).write_bytes(bytes([i % 256]) * 4096)
        os.utime(media / name, (1_700_000_000 + 3600 * i, 1_700_000_000 + 3600 * i))
    by_request: dict[str, list[dict]] = {}
    for name in names:
        url = f"/media/{name}"
        kind = name.rsplit(".", 1)[1]
        for label, r in (("get", client.get(url)), ("head", client.head(url)),
                         ("range", client.get(url, headers={"Range": "bytes=0-99"})),
                         ("revalidate", client.get(url, headers={"If-None-Match": f'"{name}"'}))):
            assert "last-modified" not in r.headers, (label, r.headers)
            assert r.headers["etag"] == f'"{name}"', (label, r.headers)
            by_request.setdefault(f"{kind} {label}", []).append(normalized(r.headers))
    for request, seen in by_request.items():
        assert all(h == seen[0] for h in seen), (request, seen)
    # Pages and static files: the ETag is the content's hash, whatever the file's time.
    for url, path in (("/study/thesis", STATIC_DIR / "participant.html"), ("/dashboard", STATIC_DIR / "dashboard.html"),
                      ("/static/participant.js", STATIC_DIR / "participant.js"),
                      ("/static/style.css", STATIC_DIR / "style.css")):
        before = client.get(url).headers
        st = path.stat()
        try:
            os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 7_000_000_000))
            after = client.get(url).headers
        finally:
            os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
        assert "last-modified" not in before and normalized(before) == normalized(after), (url, before, after)
        assert before["etag"].strip('"') == hashlib.sha256(path.read_bytes()).hexdigest()[:32]
    # The participant API and the entry page: every answer of one endpoint carries the same headers, in every
    # session and whichever side the hybrid is on.
    api: dict[str, list] = {}
    for _ in range(2):
        api.setdefault("/", []).append(client.get("/", follow_redirects=False).headers)
        api.setdefault("study", []).append(client.get("/api/v1/studies/thesis").headers)
        r = client.post("/api/v1/studies/thesis/sessions", json={"consent": True})
        api.setdefault("create", []).append(r.headers)
        sid, headers = r.json()["session_id"], {"Authorization": f"Bearer {r.json()['token']}"}
        api.setdefault("demographics", []).append(client.put(
            f"/api/v1/sessions/{sid}/demographics", json={"gamer": "no", "tech_savvy": "no"}, headers=headers).headers)
        while (r := client.get(f"/api/v1/sessions/{sid}/next", headers=headers)).status_code == 200:
            api.setdefault("next", []).append(r.headers)
            api.setdefault("vote", []).append(vote(client, sid, headers, r.json()["trial_id"], "left_much").headers)
            api.setdefault("state", []).append(client.get(f"/api/v1/sessions/{sid}", headers=headers).headers)
        api.setdefault("withdraw", []).append(client.post(f"/api/v1/sessions/{sid}/withdraw", headers=headers).headers)
    assert len(api["vote"]) == 32
    for endpoint, seen in api.items():
        keep = [{k: v for k, v in h.items() if k not in ("date", "content-length")} for h in seen]
        assert all(h == keep[0] for h in keep), endpoint


# --- 2: NaN, Infinity and lone surrogates are 422 naming the field; every response has the headers -----------

def raw(client, method, url, text, headers=None):
    return client.request(method, url, content=text.encode(), headers={"content-type": "application/json",
                                                                      **(headers or {})})


@pytest.mark.parametrize("number", ["NaN", "Infinity", "-Infinity"])
def test_non_finite_numbers_are_422_naming_the_field(client, study, number):
    sid, headers = start(client)
    trial = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()["trial_id"]
    url = f"/api/v1/sessions/{sid}/trials/{trial}/vote"
    for text, loc in ((f'{{"choice": "equal", "rt_ms": {number}, "idempotency_key": "a"}}', ["body", "rt_ms"]),
                      (f'{{"choice": "equal", "rt_ms": 5, "idempotency_key": "a", "fps": {number}}}',
                       ["body", "fps"]),
                      (f'{{"choice": "equal", "rt_ms": 5, "idempotency_key": "a", "q": {{"x": [1, {number}]}}}}',
                       ["body", "q", "x", 1])):
        r = raw(client, "POST", url, text, headers)
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == loc, (text, r.status_code, r.text)
        assert all(h in r.headers for h in SECURITY)
    r = raw(client, "POST", "/api/v1/studies/thesis/sessions", f'{{"consent": {number}}}')
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "consent"]
    r = raw(client, "POST", f"/api/v1/sessions/{sid}/events", f'{{"kind": "error", "trial_id": {number}}}', headers)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "trial_id"]


def test_lone_surrogates_and_invalid_utf8_are_422_naming_the_field(client, study):
    sid, headers = start(client)
    trial = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()["trial_id"]
    cases = [
        ("POST", f"/api/v1/sessions/{sid}/trials/{trial}/vote",
         '{"choice": "equal", "rt_ms": 5, "idempotency_key": "\\ud800"}', ["body", "idempotency_key"]),
        ("PUT", f"/api/v1/sessions/{sid}/demographics", '{"gamer": "\\udfff", "tech_savvy": "no"}',
         ["body", "gamer"]),
        ("POST", "/api/v1/studies/thesis/sessions", '{"consent": true, "external": {"PROLIFIC_PID": "x\\ud83d"}}',
         ["body", "external", "PROLIFIC_PID"]),
        ("POST", f"/api/v1/sessions/{sid}/events", '{"kind": "error", "detail": {"\\ud800": 1}}',
         ["body", "detail", "\ufffd"]),
    ]
    for method, url, text, loc in cases:
        r = raw(client, method, url, text, headers)
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == loc, (text, r.status_code, r.text)
    r = client.post("/api/v1/studies/thesis/sessions", content=b'{"consent": true, "external": {"A": "\xff"}}',
                    headers={"content-type": "application/json"})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body"]
    # The valid spelling of the same characters is stored as given.
    ok = vote(client, sid, headers, trial, key="\U0001f3ac \u00fc")
    assert ok.status_code == 201


def test_every_status_carries_the_security_headers(client, study, researcher_headers):
    app = client.app

    def boom() -> None:
        raise RuntimeError("a bug")

    def database_gone() -> None:
        raise OperationalError("SELECT 1", {}, Exception("server closed the connection"))

    app.add_api_route("/test-boom", boom)
    app.add_api_route("/test-db", database_gone)
    app.state.login_limiter = LoginLimiter(per_pair=1)
    client.post("/api/v1/auth/token", data={"username": RESEARCHER[0], "password": "wrong one"})
    responses = {
        404: client.get("/api/v1/studies/nope"),
        405: client.put("/api/v1/data-dictionary"),
        413: client.post("/api/v1/studies/thesis/sessions", content=b"x" * 70_000),
        422: client.post("/api/v1/studies/thesis/sessions", json={"consent": False}),
        429: client.post("/api/v1/auth/token", data={"username": RESEARCHER[0], "password": "wrong again"}),
        500: client.get("/test-boom"),
        503: client.get("/test-db"),
    }
    for status, r in responses.items():
        assert r.status_code == status, (status, r.status_code, r.text)
        assert all(h in r.headers for h in SECURITY), (status, r.headers)
    assert responses[500].json() == {"detail": "internal error; nothing was stored"}


def test_a_hostile_body_keeps_the_connection_usable(db, engine, tmp_path, study):
    settings = Settings(var_dir=tmp_path / "var", secret_key="test-secret-0123456789abcdef0123456789")
    app = create_app(settings, engine, run_migrations=False)
    app.dependency_overrides[get_session] = lambda: db
    with live_server(app) as url:
        conn = http.client.HTTPConnection(url.removeprefix("http://"), timeout=10)
        for body in (b'{"consent": NaN}', b'{"consent": true, "external": {"A": "\\ud800"}}'):
            conn.request("POST", "/api/v1/studies/thesis/sessions", body=body,
                         headers={"content-type": "application/json"})
            r = conn.getresponse()
            r.read()
            assert r.status == 422 and r.getheader("x-frame-options") == "DENY"
        conn.request("GET", "/api/v1/studies/thesis")  # the same keep-alive connection
        r = conn.getresponse()
        assert r.status == 200 and json.loads(r.read())["slug"] == "thesis"
        conn.close()


# --- 3: login throttling cannot lock the researcher out --------------------------------------------------------

def login(c: TestClient, password: str, email: str = RESEARCHER[0]):
    return c.post("/api/v1/auth/token", data={"username": email, "password": password})


def test_login_throttle_per_address_and_account_lets_the_researcher_in(client, db):
    create_researcher(db, *RESEARCHER)
    clock = Clock()
    client.app.state.login_limiter = LoginLimiter(per_pair=10, per_address=50, account_free=10, max_delay_s=60,
                                                  window_s=900, clock=clock)
    attacker = client_from(client.app, "203.0.113.9")
    codes = [login(attacker, f"guess {i}").status_code for i in range(12)]
    assert codes == [401] * 10 + [429, 429]
    assert login(attacker, RESEARCHER[1]).status_code == 429  # that address is throttled for that account
    researcher = client_from(client.app, "198.51.100.7")
    assert login(researcher, RESEARCHER[1]).status_code == 200  # the account is not locked
    clock.now += 901
    assert login(attacker, "guess again").status_code == 401  # the window has passed


def test_login_throttle_per_address_across_accounts(client, db):
    create_researcher(db, *RESEARCHER)
    client.app.state.login_limiter = LoginLimiter(per_pair=10, per_address=5, clock=Clock())
    sprayer = client_from(client.app, "203.0.113.10")
    codes = [login(sprayer, "password123", f"user{i}@example.org").status_code for i in range(7)]
    assert codes == [401] * 5 + [429, 429]
    assert login(sprayer, RESEARCHER[1]).status_code == 429
    assert login(client_from(client.app, "198.51.100.8"), RESEARCHER[1]).status_code == 200


def test_login_many_addresses_slow_the_account_progressively_but_never_lock_it(client, db):
    create_researcher(db, *RESEARCHER)
    clock = Clock()
    client.app.state.login_limiter = LoginLimiter(per_pair=10, per_address=50, account_free=3, max_delay_s=8,
                                                  window_s=900, clock=clock)
    bots = [client_from(client.app, f"203.0.113.{i}") for i in range(1, 30)]
    for bot in bots[:3]:  # each address fails once: the account's free failures
        assert login(bot, "wrong").status_code == 401
    waits = []
    for step in range(6):
        bot = bots[step % 3]  # addresses that have failed before
        r = login(bot, "wrong")
        assert r.status_code == 429, step
        waits.append(int(r.headers["retry-after"]))
        clock.now += waits[-1]
        assert login(bot, "wrong").status_code == 401, step  # after the wait one more guess goes through
    assert waits == [1, 2, 4, 8, 8, 8]  # progressive, capped: slowed, never blocked
    # Meanwhile the right password gets in from an address without failures ...
    assert login(client_from(client.app, "198.51.100.9"), RESEARCHER[1]).status_code == 200
    # ... and from an address that has logged in before, even after a typo.
    office = client_from(client.app, "198.51.100.10")
    assert login(office, RESEARCHER[1]).status_code == 200
    assert login(office, "typo").status_code == 401
    assert login(office, RESEARCHER[1]).status_code == 200
    # A bot that failed before is still slowed, even with the right password.
    assert login(bots[0], RESEARCHER[1]).status_code == 429


# --- 4: no redirect from the Host header; allowed hosts ----------------------------------------------------------

def test_no_redirect_is_built_from_the_host_header(client, study):
    r = client.get("/api/v1/studies/thesis/", headers={"Host": "evil.example"}, follow_redirects=False)
    assert "evil.example" not in r.headers.get("location", "") and r.status_code == 404
    r = client.get("/", headers={"Host": "evil.example"}, follow_redirects=False)
    assert r.status_code == 307 and r.headers["location"] == "/s/thesis"


def test_allowed_hosts(db, engine, tmp_path, study, monkeypatch):
    monkeypatch.setenv("ANIMSTUDY_ALLOWED_HOSTS", "study.example.org, *.lab.example.org")
    settings = Settings(var_dir=tmp_path / "var", secret_key="test-secret-0123456789abcdef0123456789")
    assert settings.allowed_hosts == ["study.example.org", "*.lab.example.org"]
    app = create_app(settings, engine, run_migrations=False)
    app.dependency_overrides[get_session] = lambda: db
    c = TestClient(app)
    for host, status in (("study.example.org", 200), ("a.lab.example.org", 200), ("evil.example", 400),
                         ("study.example.org.evil.example", 400)):
        r = c.get("/api/v1/studies/thesis", headers={"Host": host})
        assert r.status_code == status, host
        assert r.headers["x-frame-options"] == "DENY"
    assert Settings().allowed_hosts == ["study.example.org", "*.lab.example.org"]
    monkeypatch.delenv("ANIMSTUDY_ALLOWED_HOSTS")
    assert Settings().allowed_hosts == ["*"]


# --- 5: strict types on the participant API ------------------------------------------------------------------------

def test_participant_bodies_are_strictly_typed(client, study):
    for consent in ("true", 1, "1", "yes", [True]):
        r = client.post("/api/v1/studies/thesis/sessions", json={"consent": consent})
        assert r.status_code == 422, consent
    sid, headers = start(client)
    trial = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()["trial_id"]
    for rt_ms in ("100", 100.5, True, None):
        r = client.post(f"/api/v1/sessions/{sid}/trials/{trial}/vote",
                        json={"choice": "equal", "rt_ms": rt_ms, "idempotency_key": "k"}, headers=headers)
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "rt_ms"], rt_ms
    r = client.post(f"/api/v1/sessions/{sid}/trials/{trial}/vote",
                    json={"choice": "equal", "rt_ms": 100, "idempotency_key": 7}, headers=headers)
    assert r.status_code == 422
    r = client.post(f"/api/v1/sessions/{sid}/events", json={"kind": "error", "trial_id": [trial]},
                    headers=headers)
    assert r.status_code == 422
    assert vote(client, sid, headers, trial, rt_ms=100).status_code == 201


# --- 6: HTTP details ------------------------------------------------------------------------------------------------

def test_chunked_body_over_the_limit_is_413(client, study):
    def chunks():
        for _ in range(20):
            yield b" " * 4096
    r = client.post("/api/v1/studies/thesis/sessions", content=chunks(), headers={"content-type": "application/json"})
    assert "content-length" not in r.request.headers and r.status_code == 413


def test_ranges_head_and_conditional_requests(client, study):
    media = client.app.state.settings.media_dir
    media.mkdir(parents=True, exist_ok=True)
    name = "00112233445566778899aabb.mp4"
    payload = bytes(range(256)) * 8
    (media / name).write_bytes(payload)
    url = f"/media/{name}"
    for bad in ("bytes=500-100", "bytes=abc", "bytes=", "pages=0-10"):  # invalid: ignored
        r = client.get(url, headers={"Range": bad})
        assert r.status_code == 200 and r.content == payload, bad
    r = client.get(url, headers={"Range": f"bytes={len(payload)}-"})
    assert r.status_code == 416 and r.headers["content-range"] == f"bytes */{len(payload)}"
    r = client.get(url, headers={"Range": "bytes=10-19"})
    assert r.status_code == 206 and r.content == payload[10:20]
    r = client.get(url, headers={"Range": "bytes=10-19", "If-Range": '"something else"'})
    assert r.status_code == 200 and r.content == payload
    for path in (url, "/study/thesis", "/dashboard", "/static/participant.js"):
        get, head = client.get(path), client.head(path)
        assert head.status_code == 200 and head.content == b"", path
        assert normalized(head.headers) == normalized(get.headers), path
        etag = get.headers["etag"]
        for match in (etag, f"W/{etag}", f'"nope", {etag}', "*"):
            r = client.get(path, headers={"If-None-Match": match})
            assert r.status_code == 304 and r.content == b"" and r.headers["etag"] == etag, (path, match)
        assert client.get(path, headers={"If-None-Match": '"nope"'}).status_code == 200
    assert client.head("/", follow_redirects=False).status_code == 307


# --- 7: a finished session's demographics are final -----------------------------------------------------------

def test_demographics_of_a_completed_or_withdrawn_session_are_409(client, study, db):
    sid, headers = start(client)
    answers = {"gamer": "no", "tech_savvy": "yes"}
    assert client.put(f"/api/v1/sessions/{sid}/demographics", json=answers, headers=headers).status_code == 200
    answer_all(client, sid, headers)
    r = client.put(f"/api/v1/sessions/{sid}/demographics", json={"gamer": "yes", "tech_savvy": "yes"},
                   headers=headers)
    assert r.status_code == 409
    from server.participants.models import ParticipantSession

    ps = db.get(ParticipantSession, sid)
    assert ps.answers == answers
    sid2, headers2 = start(client)
    client.post(f"/api/v1/sessions/{sid2}/withdraw", headers=headers2)
    with pytest.raises(Conflict):
        service.set_answers(db, db.get(ParticipantSession, sid2), {"gamer": "yes", "tech_savvy": "yes"})


# --- 8: new sessions per address are limited ----------------------------------------------------------------------

def test_new_sessions_per_address_are_limited(client, study):
    assert Settings().sessions_per_minute == 60
    clock = Clock()
    client.app.state.session_limiter = RateLimiter(3, window_s=60.0, clock=clock)
    codes = [client.post("/api/v1/studies/thesis/sessions", json={"consent": True}) for _ in range(4)]
    assert [r.status_code for r in codes] == [201, 201, 201, 429]
    assert 1 <= int(codes[-1].headers["retry-after"]) <= 60
    other = client_from(client.app, "198.51.100.20")
    assert other.post("/api/v1/studies/thesis/sessions", json={"consent": True}).status_code == 201
    clock.now += 61
    assert client.post("/api/v1/studies/thesis/sessions", json={"consent": True}).status_code == 201


def test_the_default_session_limit_is_60_per_minute(client, study):
    codes = [client.post("/api/v1/studies/thesis/sessions", json={"consent": True}).status_code for _ in range(61)]
    assert codes == [201] * 60 + [429]


# --- 9: external ids exported, formulas neutralized ----------------------------------------------------------------

@pytest.mark.parametrize("start_char", ["=", "+", "-", "@", "\t", "\r"])
def test_external_ids_are_exported_and_formulas_neutralized(client, study, researcher_headers, start_char):
    pid = f"{start_char}HYPERLINK(\"http://evil.example\",\"x\")"
    external = {"PROLIFIC_PID": pid, "STUDY_ID": "study-64", "SESSION_ID": f"{start_char}1+1"}
    sid, headers = start(client, **external)
    trial = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()
    assert vote(client, sid, headers, trial["trial_id"], "left_much").status_code == 201
    text = client.get("/api/v1/studies/thesis/export.csv", headers=researcher_headers).text
    row = next(csv.DictReader(io.StringIO(text, newline="")))
    assert row["PROLIFIC_PID"] == "'" + pid
    assert row["STUDY_ID"] == "study-64"
    assert row["SESSION_ID"] == f"'{start_char}1+1"
    assert int(row["score"]) in (-2, 2)  # numbers stay numbers
    data = client.get("/api/v1/studies/thesis/export.json", headers=researcher_headers).json()
    assert {k: data["votes"][0][k] for k in external} == external  # the JSON keeps the text exactly as given
    dictionary = client.get("/api/v1/data-dictionary").text
    assert all(name in dictionary for name in external)
