"""The simulators moved from ``lidarjax.datasets`` to ``lidarjax.sim``: the old names still
resolve (lazily, with a ``DeprecationWarning`` naming the new place), and importing
``lidarjax.datasets`` does not import ``lidarjax.sim``."""

from __future__ import annotations

import subprocess
import sys
import warnings

import pytest

import lidarjax.datasets as datasets
import lidarjax.sim as sim

# Every public name the old lidarjax.datasets exported from its simulator modules
# (_synthetic, _polygons, _synpeb, _urban) that now lives in lidarjax.sim.
MOVED = (
    "OfficeWorld",
    "make_office",
    "simulate_scans",
    "random_polygon",
    "simulate_polygon_scan",
    "ConvexPolyhedron",
    "SynPEBScene",
    "cast_rays",
    "make_synpeb_scene",
    "simulate_synpeb_scan",
    "synpeb_scan",
    "synpeb_split",
    "BOX_KINDS",
    "HDL32E_ELEVATIONS_DEG",
    "POLE_KINDS",
    "LidarSpec",
    "UrbanScan",
    "UrbanWorld",
    "hdl32e",
    "make_urban_world",
    "simulate_urban_scan",
    "simulate_urban_scans",
    "urban_session",
    "wheel_odometry",
)

# Names of those modules that are file I/O or plain containers and stay in datasets.
STAYED = (
    "SynPEBScan",
    "load_synpeb_pcd",
    "write_synpeb_pcd",
    "UrbanTrajectory",
    "load_urban_trajectory",
)


def test_the_moved_list_is_the_forwarding_table():
    assert set(MOVED) == set(datasets._MOVED_TO_SIM)


@pytest.mark.parametrize("name", MOVED)
def test_moved_name_resolves_from_both_places_and_the_old_one_warns(name):
    new = getattr(sim, name)
    with pytest.warns(DeprecationWarning, match=rf"lidarjax\.sim\.{name}\b"):
        old = getattr(datasets, name)
    assert old is new
    assert name not in vars(datasets)  # forwarded on each access, not cached in datasets


@pytest.mark.parametrize("name", ["simulate_synpeb_scan", "make_office", "LidarSpec"])
def test_from_import_of_an_old_name_warns(name):
    with pytest.warns(DeprecationWarning, match=rf"lidarjax\.sim\.{name}\b"):
        exec(f"from lidarjax.datasets import {name} as got", {})


@pytest.mark.parametrize("name", STAYED)
def test_io_names_stay_in_datasets_without_warning(name):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert getattr(datasets, name) is vars(datasets)[name]


def test_moved_names_are_listed_by_dir_and_unknown_names_still_fail():
    assert set(MOVED) <= set(dir(datasets))
    with pytest.raises(AttributeError, match="no_such_name"):
        datasets.no_such_name  # noqa: B018
    with pytest.raises(ImportError):
        exec("from lidarjax.datasets import no_such_name", {})


def test_sim_has_one_name_per_function():
    # the old in-module aliases are gone: the urban simulators have only their urban names
    for alias in ("simulate_scan",):
        assert not hasattr(sim, alias)
    assert sim.simulate_scans is not sim.simulate_urban_scans
    assert sim.simulate_urban_scan.__name__ == "simulate_urban_scan"
    assert sim.simulate_urban_scans.__name__ == "simulate_urban_scans"


def test_importing_datasets_does_not_import_sim():
    code = (
        "import sys, lidarjax.datasets; "
        "assert 'lidarjax.sim' not in sys.modules, sorted(m for m in sys.modules "
        "if m.startswith('lidarjax'))"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
