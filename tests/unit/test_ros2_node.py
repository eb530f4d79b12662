"""The rclpy node's parts that run without ROS 2: it imports, says what is missing, and finds its services.

The node itself cannot run here (no rclpy); docs/ros2.md says so. Its logic lives in the core, tested elsewhere.
"""

from __future__ import annotations

import sys
import types

import pytest

from vpengine.ros2 import node


def test_the_module_imports_without_ros2_and_main_names_what_is_missing(monkeypatch):
    monkeypatch.setitem(sys.modules, "rclpy", None)  # make sure: an import of rclpy fails
    with pytest.raises(RuntimeError, match=r"rclpy is not installed .* `vpengine ros2` runs the same topics"):
        node.main([])
    with pytest.raises(RuntimeError, match="rclpy is not installed"):
        node.build_node()


def _fake_srv_package(monkeypatch, name: str, complete: bool = True) -> tuple[type, type]:
    change = type("ChangeModelRate", (), {})
    names = type("GetModelNames", (), {})
    pkg = types.ModuleType(name)
    srv = types.ModuleType(f"{name}.srv")
    srv.ChangeModelRate = change
    if complete:
        srv.GetModelNames = names
    monkeypatch.setitem(sys.modules, name, pkg)
    monkeypatch.setitem(sys.modules, f"{name}.srv", srv)
    return change, names


def test_services_come_from_the_first_package_that_has_both(monkeypatch):
    for pkg in node.SERVICE_PACKAGES:
        monkeypatch.setitem(sys.modules, pkg, None)
        monkeypatch.setitem(sys.modules, f"{pkg}.srv", None)
    assert node.find_services() is None  # -> the node falls back to std_srvs/Trigger and rate.<model> parameters
    change, names = _fake_srv_package(monkeypatch, "vp_engine_ros")  # the VPEngine paper's package
    assert node.find_services() == (change, names)
    _fake_srv_package(monkeypatch, "vpengine_interfaces", complete=False)  # incomplete: skipped
    assert node.find_services() == (change, names)
    mine = _fake_srv_package(monkeypatch, "vpengine_interfaces")
    assert node.find_services() == mine


def test_head_services_come_from_a_package_that_has_both_and_are_optional(monkeypatch):
    for pkg in node.SERVICE_PACKAGES:
        monkeypatch.setitem(sys.modules, pkg, None)
        monkeypatch.setitem(sys.modules, f"{pkg}.srv", None)
    assert node.find_services(("AddHead", "RemoveHead")) is None  # -> the add_head / remove_head topics only
    _fake_srv_package(monkeypatch, "vpengine_interfaces")  # rate services, no head services
    assert node.find_services(("AddHead", "RemoveHead")) is None
    srv = sys.modules["vpengine_interfaces.srv"]
    srv.AddHead, srv.RemoveHead = type("AddHead", (), {}), type("RemoveHead", (), {})
    assert node.find_services(("AddHead", "RemoveHead")) == (srv.AddHead, srv.RemoveHead)
    assert node.find_services() == (srv.ChangeModelRate, srv.GetModelNames)
