"""What a manager stores in rosmaster's parameter tree through setParam, charged key by
key as rosmaster keeps it (interceptor/param_quota.py)."""

from __future__ import annotations

import pytest

from cryptoros.errors import PolicyDenied
from interceptor.param_quota import ParamQuota


def test_new_keys_are_refused_past_the_key_quota_and_nothing_changes():
    quota = ParamQuota(max_keys=5, max_bytes=1 << 20)
    quota.set("b", "/n", {})  # the private namespace: one key
    for i in range(4):
        quota.set("b", f"/n/k{i}", i)
    assert quota.usage("b")[0] == 5
    with pytest.raises(PolicyDenied) as refused:
        quota.set("b", "/n/k4", 4)
    assert refused.value.reason == "param_quota"
    assert quota.usage("b")[0] == 5
    quota.set("b", "/n/k0", "overwritten")  # replacing a key does not grow the count
    quota.delete("/n/k1")  # deleteParam frees it
    quota.set("b", "/n/k4", 4)
    assert quota.usage("b")[0] == 5


def test_bytes_count_names_and_values_and_a_smaller_write_is_allowed_over_quota():
    quota = ParamQuota(max_keys=100, max_bytes=1000)
    quota.set("b", "/n/big", "x" * 900)
    assert quota.usage("b") == (2, len("n") + len("big") + 900)
    with pytest.raises(PolicyDenied):
        quota.set("b", "/n/more", "y" * 200)
    quota.set("b", "/n/big", "x" * 10)  # shrinking is always allowed
    quota.set("b", "/n/more", "y" * 200)


def test_a_dict_value_is_charged_per_member_and_replaced_whole():
    quota = ParamQuota(max_keys=100, max_bytes=1 << 20)
    quota.set("b", "/n/cfg", {"a": 1, "b": {"c": "xy", "d": []}})
    assert quota.usage("b")[0] == 1 + 1 + 1 + 1 + 1 + 1  # /n, cfg, a, b, c, d
    quota.set("b", "/n/cfg", 5)  # replaces the namespace with one value
    assert quota.usage("b")[0] == 2
    quota.set("b", "/n/cfg/x", 1)  # the value on the way becomes a namespace
    assert quota.usage("b")[0] == 3


def test_deleting_a_namespace_frees_what_every_manager_wrote_below_it():
    quota = ParamQuota(max_keys=100, max_bytes=1 << 20)
    quota.set("a", "/shared/x", 1)
    quota.set("b", "/shared/y", 2)
    assert quota.usage("b") == (1, 1 + 8)  # /shared is a's: it made it
    quota.delete("/shared")
    assert quota.all_usage() == {}


def test_the_namespaces_a_delete_leaves_stay_charged():
    """rosmaster keeps /n/k_i as an empty namespace after deleteParam /n/k_i/x: a
    set-and-delete churn of fresh names is still bounded by the quota."""
    quota = ParamQuota(max_keys=10, max_bytes=1 << 20)
    refused = 0
    for i in range(20):
        try:
            quota.set("b", f"/n/k{i}/x", 1)
        except PolicyDenied:
            refused += 1
        quota.delete(f"/n/k{i}/x")
    assert refused > 0 and quota.usage("b")[0] <= 10


def test_a_root_write_replaces_everything_and_clear_forgets_everything():
    quota = ParamQuota(max_keys=100, max_bytes=1 << 20)
    quota.set("a", "/a/x", 1)
    quota.set("b", "/", {"b": {"y": 2}})
    assert quota.all_usage() == {"b": (2, 1 + 1 + 8)}
    quota.set("b", "/", 5)  # rosmaster refuses it: nothing changes
    assert quota.usage("b")[0] == 2
    quota.clear()
    assert quota.all_usage() == {}


def test_items_are_what_a_restarted_rosmaster_gets_back():
    quota = ParamQuota(100, 10_000)
    quota.set("a", "/robot/speed", 1.5)
    quota.set("a", "/robot/limits", {"max": 2, "min": {}})
    quota.set("b", "/gone/x", "y")
    quota.set("b", "/other", [1, "two"])
    quota.delete("/gone/x")
    quota.set("a", "/robot/name", "r1")
    quota.set("a", "/robot/name", "r2")  # replaced: only the last value
    items = dict(quota.items())
    assert items == {"/robot/speed": 1.5, "/robot/limits/max": 2, "/robot/limits/min": {}, "/gone": {},
                     "/robot/name": "r2", "/other": [1, "two"]}
    quota.set("a", "/robot", 7)  # a value replaces the namespace and all below it
    assert dict(quota.items()) == {"/robot": 7, "/gone": {}, "/other": [1, "two"]}
    quota.clear()
    assert quota.items() == []


def test_a_date_is_charged_for_its_text():
    from xmlrpc.client import DateTime

    from interceptor.param_quota import value_bytes

    assert value_bytes(DateTime("20261128T16:05:09")) == 17
    assert value_bytes(DateTime("x" * 900_000)) == 900_000
