"""One request with its retries, within its deadline, as steps for the fetch schedule's driver (sans-IO), and the
playback log's line for each attempt."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from stgs.client.fetch.download import DownloadSettings
from stgs.client.fetch.steps import Abandoned, Done, Failed, Outcome, Request, Steps, Wait
from stgs.client.playlog import GOPRecord


def first_attempt(request: Request, settings: DownloadSettings) -> Request:
    """The request's first attempt, with the whole deadline (`DownloadSettings.total_timeout_s`) before it."""
    return dataclasses.replace(request, time_left=settings.total_timeout_s)


def with_retries(request: Request, rec: GOPRecord, settings: DownloadSettings, on_retry: Callable[[], None],
                 first: Failed | None = None) -> Steps[Outcome]:
    """`request` until it succeeds, fails for good or runs out of retries or deadline, backing off between
    attempts (`Wait`); `first`: the failed first attempt, made in a joint request. Each attempt is recorded in
    `rec`; `on_retry` is called before each retry."""
    outcome: Outcome | None = first
    spent = 0.0 if first is None else first.seconds
    for attempt in range(0 if first is None else 1, settings.retries + 1):
        if isinstance(outcome, Failed):
            wait = settings.backoff(attempt)
            if spent + wait >= settings.total_timeout_s:
                outcome = Failed(f"{outcome.reason}; no answer within {settings.total_timeout_s:g} s",
                                 retryable=True, seconds=spent)
                break
            on_retry()
            rec.events.append(f"retry {attempt} of the {request.kind} of {request.rep}: {outcome.reason}")
            yield Wait(wait)
            spent += wait
        outcome = yield dataclasses.replace(request, time_left=settings.total_timeout_s - spent)
        spent += outcome.seconds
        record(rec, request, outcome)
        if not (isinstance(outcome, Failed) and outcome.retryable):
            break
    else:
        if settings.retries:
            assert isinstance(outcome, Failed)  # the loop ran out on a retryable failure
            outcome = Failed(f"{outcome.reason} (after {settings.retries + 1} attempts)", retryable=True,
                             seconds=spent)
    assert outcome is not None  # `first`, or an attempt's
    return outcome


def record(rec: GOPRecord, request: Request, outcome: Outcome) -> None:
    """The attempt's line in the GOP's record."""
    rec.requests.append({"kind": request.kind, "rep": request.rep, "outcome": describe(outcome)})


def describe(outcome: Outcome | None) -> str:
    if isinstance(outcome, Done):
        return f"{outcome.nbytes} bytes"
    if isinstance(outcome, Abandoned):
        return f"abandoned after {outcome.nbytes} bytes"
    if isinstance(outcome, Failed):
        return f"failed: {outcome.reason}"
    return "none"
