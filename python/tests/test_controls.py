"""The farm controls: pause, resume, priority, requeue, retry, delete, and the filtered job
list."""

from __future__ import annotations

import time
import uuid

import pytest

import omis

#: A job that runs long enough to be controlled (no test waits for it to finish).
LONG = {"resolution": (24, 16), "spp": 60000, "pass_size": 1, "max_pass_size": 1}
SMALL = {"resolution": (24, 16), "spp": 2, "pass_size": 1, "max_pass_size": 1}


def test_pause_resume_and_priority(client: omis.Client) -> None:
    job = client.submit("cornell-box", name=f"pause-{uuid.uuid4()}", priority=1, **LONG)
    assert job.status()["priority"] == 1
    st = job.pause()
    assert st["state"] == "paused"
    assert st["eta_s"] is None
    with pytest.raises(omis.ServiceError) as e:
        job.pause()
    assert e.value.status == 409 and e.value.field == "id"
    assert job.set_priority(7)["priority"] == 7
    time.sleep(0.2)
    st = job.resume()
    assert st["state"] in ("queued", "running")
    assert st["paused_s"] > 0
    job.cancel()
    with pytest.raises(omis.ServiceError) as e:
        job.set_priority(1)
    assert e.value.status == 409


def test_requeue_refuses_a_job_that_has_not_failed(client: omis.Client) -> None:
    job = client.submit("cornell-box", **LONG)
    with pytest.raises(omis.ServiceError) as e:
        job.requeue()
    assert e.value.status == 409 and "failed" in e.value.message
    job.cancel()


def test_retry_makes_a_new_job_and_delete_removes_it(client: omis.Client) -> None:
    name = f"retry-{uuid.uuid4()}"
    job = client.submit("cornell-box", name=name, priority=2, **LONG)
    with pytest.raises(omis.ServiceError) as e:
        job.delete()
    assert e.value.status == 409
    job.cancel()
    again = job.retry()
    assert again.id != job.id
    st = again.status()
    assert st["retry_of"] == job.id
    assert (st["name"], st["priority"]) == (name, 2)
    again.cancel()
    for j in (job, again):
        j.delete()
        with pytest.raises(omis.ServiceError) as e:
            j.status()
        assert e.value.status == 404
    assert client.jobs(name=name) == []


def test_jobs_filters_by_state_name_and_time(client: omis.Client) -> None:
    tag = f"list-{uuid.uuid4()}"
    t0 = time.time() - 1
    done = client.submit("cornell-box", name=f"{tag}-done", **SMALL)
    done.wait(progress=False, timeout=120)
    cancelled = client.submit("cornell-box", name=f"{tag}-cancelled", **LONG)
    cancelled.cancel()
    assert [j.id for j in client.jobs(name=tag.upper())] == [done.id, cancelled.id]
    assert [j.id for j in client.jobs(state="cancelled", name=tag)] == [cancelled.id]
    assert [j.id for j in client.jobs(state=("done", "cancelled"), name=tag, since=t0)] == [
        done.id,
        cancelled.id,
    ]
    assert client.jobs(name=tag, since=time.time() + 3600) == []
    with pytest.raises(omis.ServiceError) as e:
        client.jobs(state="finished")
    assert e.value.status == 400 and e.value.field == "state"
