"""One error line from a failed Ray task (risp_data.ray_support): Ray itself is an optional extra that CI does not
install, so its exception types are stood in for by classes shaped like ray.exceptions' (a ``cause`` attribute
holding the task's own exception, a multi-line text holding the worker's traceback)."""

import types

import pytest

from risp_data.errors import RispError
from risp_data.ray_support import first_line, ray_errors

TRACEBACK = "ray::run() (pid=4242, ip=10.0.0.1)\n  File \"x.py\", line 5, in run\n    raise RispError(...)\nRispError: {msg}"


class RayError(Exception):
    pass


class RayTaskError(RayError):
    def __init__(self, cause):
        super().__init__(TRACEBACK.format(msg=cause))
        self.cause = cause


@pytest.fixture
def fake_ray(monkeypatch):
    module = types.SimpleNamespace(exceptions=types.SimpleNamespace(RayError=RayError))
    monkeypatch.setitem(__import__("sys").modules, "ray", module)


def test_first_line_is_the_task_s_own_message():
    error = RayTaskError(RispError("shard 3: no usable libLLVM"))
    assert "\n" in str(error)  # what ray.get raises is the worker's traceback
    assert first_line(error) == "shard 3: no usable libLLVM"


def test_an_actor_that_died_in_its_constructor_gives_its_error():
    """ActorDiedError has no cause: its text embeds the creation task's traceback, whose last line is the error."""
    text = ("The actor died because of an error raised in its creation task, ray::ShardActor.__init__() (pid=9, "
            "ip=10.0.0.2)\n  File \"generate.py\", line 12, in __init__\n    self.renderer = make_renderer(job)\n"
            "risp_data.errors.RispError: no usable libLLVM (>= 16) found")
    assert first_line(RayError(text)) == "risp_data.errors.RispError: no usable libLLVM (>= 16) found"


def test_first_line_without_a_cause_skips_blank_lines():
    assert first_line(RayError("\n\n  the raylet died  \nmore")) == "the raylet died"
    assert first_line(RayError("")) == "RayError"


def test_ray_errors_makes_one_line(fake_ray):
    with pytest.raises(RispError) as info:
        with ray_errors("cell control/rod/ours/r0"):
            raise RayTaskError(ValueError("bad\nsecond line"))
    assert str(info.value) == "cell control/rod/ours/r0 failed on Ray: bad"


def test_ray_errors_leaves_other_errors_alone(fake_ray):
    with pytest.raises(KeyError):
        with ray_errors("x"):
            raise KeyError("not Ray's")


def test_ray_errors_without_ray_imported_leaves_errors_alone(monkeypatch):
    monkeypatch.delitem(__import__("sys").modules, "ray", raising=False)
    with pytest.raises(ValueError):
        with ray_errors("x"):
            raise ValueError("no ray here")


def test_a_ray_render_starts_no_more_actors_than_the_cluster_has_cpus():
    """An actor that cannot be scheduled still receives shards from Ray's ActorPool, which then waits for it for
    ever: --workers 8 on a 4-CPU cluster starts 4 actors (and never more than the shards to render)."""
    from risp_data.generate import ray_actor_count

    assert ray_actor_count(8, 20, 4) == 4
    assert ray_actor_count(8, 3, 16) == 3
    assert ray_actor_count(2, 20, 16) == 2
    assert ray_actor_count(1, 0, 0) == 1
