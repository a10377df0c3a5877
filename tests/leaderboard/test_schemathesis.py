"""Schema fuzzing of the whole JSON API with Schemathesis (issue 13).

Every operation of ``/openapi.json`` is called with generated inputs — valid ones and, in
Schemathesis' negative mode, broken ones — once anonymously and once with a user's token, on a
seeded leaderboard. Checks: no answer is a server error (5xx), every answer's status, content
type and body match what the schema declares for it. Bounded in time: a few examples per
operation (about 25 s on a loaded 2-core machine).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import schemathesis
from fastapi import FastAPI
from hypothesis import HealthCheck, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis import GenerationMode
from schemathesis.checks import (
    content_type_conformance,
    not_a_server_error,
    response_schema_conformance,
    status_code_conformance,
)

from leaderboard import auth
from leaderboard.app import create_app
from leaderboard.settings import Settings
from tests.leaderboard import factories

MAX_EXAMPLES = 6  # per operation and token mode
CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_schema_conformance,
]


@pytest.fixture(scope="module")
def fuzzed_app(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[FastAPI, str]]:
    """An app on a seeded database (5 submissions, 6 races) and a user token for it.

    Rate limits are generous (the fuzzer sends hundreds of requests from one address); the
    limits themselves are tested in test_security.py.
    """
    data: Path = tmp_path_factory.mktemp("fuzz")
    s = Settings(
        data_dir=data,
        tracks=["oval", "bean"],
        admin_token="fuzz-admin-token-0123456789",
        rate_limit_ip="100000/minute",
        rate_limit_token="100000/minute",
        rate_limit_auth_failures="100000/minute",
    )
    app = create_app(s)
    session = app.state.sessionmaker()
    try:
        factories.seed(session, s, n_submissions=5, n_races=6)
        _, token = auth.create_user(session, name="fuzzer")
        session.commit()
    finally:
        session.close()
    yield app, token


FUZZ = settings(
    max_examples=MAX_EXAMPLES,
    deadline=None,
    derandomize=True,
    suppress_health_check=list(HealthCheck),
    database=None,
)


def _call(case: schemathesis.Case, headers: dict[str, str]) -> None:
    if headers and case.method.upper() == "DELETE" and case.path == "/api/tokens/{token_id}":
        # Revoking the fuzzer's own token would turn the rest of the run anonymous.
        case.path_parameters = {"token_id": 10**6}
    case.call_and_validate(headers=headers, checks=CHECKS)


@pytest.mark.slow
@pytest.mark.parametrize("mode", list(GenerationMode), ids=lambda m: m.value)
@pytest.mark.parametrize("with_token", [False, True], ids=["anonymous", "token"])
def test_api_conforms_to_its_schema(
    fuzzed_app: tuple[FastAPI, str], with_token: bool, mode: GenerationMode
) -> None:
    """Every operation: positive (valid) or negative (invalid) inputs, with or without a token.

    (Schemathesis' pytest plugin does not run under pytest 9 yet, so each operation's
    strategy is driven with Hypothesis here.)
    """
    app, token = fuzzed_app
    headers = {"Authorization": f"Bearer {token}"} if with_token else {}
    api = schemathesis.openapi.from_asgi("/openapi.json", app)
    operations = [result.ok() for result in api.get_all_operations()]
    assert len(operations) >= 15
    for operation in operations:

        @FUZZ
        @given(case=operation.as_strategy(generation_mode=mode))
        def run(case: schemathesis.Case) -> None:
            _call(case, headers)

        try:
            run()
        except Unsatisfiable:
            # Negative mode on an operation with no input to break (GET /api/health).
            assert mode is GenerationMode.NEGATIVE, operation.label
