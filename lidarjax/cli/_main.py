"""The ``lidarjax`` argument parser, its subcommands and the error policy.

Handlers live in sibling modules and are imported only when their subcommand runs, so
``lidarjax --help`` does not import JAX.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import textwrap
from collections.abc import Sequence

from ..distributed import HOST_DEVICES_ENV
from ._inputs import AZIMUTH_LAYOUTS, CliInputError

__all__ = ["build_parser", "main"]

PROG = "lidarjax"


def _fmt(text: str) -> str:
    return textwrap.dedent(text).strip("\n")


class _Formatter(argparse.RawDescriptionHelpFormatter):
    """Keep the hand-wrapped descriptions and examples; show the defaults that matter."""

    def _get_help_string(self, action):
        text = action.help or ""
        default = action.default
        if (
            "default" not in text
            and default is not None
            and default is not False
            and default != argparse.SUPPRESS
            and action.option_strings
        ):
            text += " (default: %(default)s)"
        return text


def _sub(subparsers, name: str, summary: str, description: str, example: str, handler: str):
    p = subparsers.add_parser(
        name,
        help=summary,
        description=_fmt(description),
        epilog="example:\n" + "\n".join("  " + ln.strip() for ln in _fmt(example).splitlines()),
        formatter_class=_Formatter,
    )
    p.set_defaults(handler=handler)
    return p


def _azimuth_layout_option(p: argparse.ArgumentParser) -> None:
    """``--azimuth-layout``: ``load_carmen``'s ``azimuth_layout`` for a CARMEN LOG."""
    p.add_argument(
        "--azimuth-layout",
        choices=AZIMUTH_LAYOUTS,
        default=None,
        help="beam azimuths of a CARMEN log: spread = evenly from -fov/2 to +fov/2 (the data "
        "README's layout); sweep = the scanner's own 1-degree (or declared resolution) steps "
        "from -90 deg, an even beam count missing its last beam (-90 ... +89 deg for 180 "
        "beams), how the shared logs' corrected poses were made (default: spread; not for "
        "ROS bags, whose scans carry their angles)",
    )


def build_parser() -> argparse.ArgumentParser:
    """The full ``lidarjax`` parser (subcommands and their options)."""
    import lidarjax

    parser = argparse.ArgumentParser(
        prog=PROG,
        description=_fmt(
            """
            lidarjax: probabilistic, differentiable lidar mapping and localization in JAX.
            Build maps from laser logs and ROS bags, localize in them with a particle
            filter, estimate trajectory and map together (decay-rate SLAM), extract
            polylines, planes and poles, fetch the registered data sets and run the
            packaged Hydra experiments. `lidarjax COMMAND --help` explains each.
            """
        ),
        epilog=_fmt(
            """
            examples:
              lidarjax info
              lidarjax map intel -o out/intel --scans 0:910:2
              lidarjax localize out/intel/map.npz intel -o out/loc --scans 1:200:2
              lidarjax experiment demo localization.particles=1000
            """
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"lidarjax {lidarjax.__version__}")
    parser.add_argument("--debug", action="store_true", help="show the full traceback of any error")
    parser.add_argument(
        "--x64", action="store_true", help="compute in float64 (JAX's default is float32)"
    )
    parser.add_argument(
        "--host-devices",
        type=int,
        metavar="N",
        help="expose the CPU as N JAX devices (XLA's host device count, set before JAX "
        "starts; sharded particle filters split over them; also passed on to `lidarjax "
        f"experiment`); default: ${HOST_DEVICES_ENV}, else JAX's default (one)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    # ---------------------------------------------------------------- info
    _sub(
        sub,
        "info",
        "versions, devices, native kernels, data and cache folders",
        """
        Print the versions of lidarjax, JAX, jaxlib and NumPy, the JAX devices and whether
        float64 is on, whether each native (C++) kernel is built and used by default, the
        folders searched for data files, the user cache and JAX's compilation cache folder.
        """,
        "lidarjax info",
        "_info:cmd_info",
    )

    # ---------------------------------------------------------------- datasets / fetch
    _sub(
        sub,
        "datasets",
        "list the registered data files",
        """
        List every registered data file: its name, whether a verified copy is found
        locally (in $LIDARJAX_DATA, ../shared/data or the user cache) and where, its size,
        and whether a download location is known (the entry's public URL or the mirror
        $LIDARJAX_DATA_URL/<relpath>).
        """,
        "lidarjax datasets",
        "_info:cmd_datasets",
    )
    p = _sub(
        sub,
        "fetch",
        "download and verify registered data files",
        """
        Download registered data files into the user cache ($LIDARJAX_CACHE, default
        ~/.cache/lidarjax) and verify their SHA-256; files found locally are only verified.
        Downloads come from $LIDARJAX_DATA_URL/<relpath> when that variable is set, else
        from the file's public URL. A wrong checksum is an error and leaves no file behind.
        """,
        "lidarjax fetch intel aces\n"
        "  LIDARJAX_DATA_URL=https://example.org/lidar-data lidarjax fetch --all",
        "_info:cmd_fetch",
    )
    p.add_argument("names", nargs="*", metavar="NAME", help="registry names (`lidarjax datasets`)")
    p.add_argument("--all", action="store_true", help="every registered file")

    # ---------------------------------------------------------------- map
    p = _sub(
        sub,
        "map",
        "build a grid map from a laser log or ROS bag",
        """
        Build a 2-D grid map from a laser log at its poses: the corrected poses of a CARMEN
        log, or the tf poses of a ROS bag. LOG is a registry name (intel, carmen/intel), a
        CARMEN .log / .log.gz file or a ROS bag (.bag, .db3, .mcap or a ROS 2 bag folder).
        The rays are traced exactly into per-cell hits, misses and travelled lengths in
        chunks of scans (a progress bar), and the chosen sensor model's map is computed from
        them: decay-rate (lambda = H / R, Eq. 7.10), reflection (mu = H / (H + M), Eq. 7.22)
        or endpoint (likelihood field). Writes into OUT: map.npz (the map, its grid and the
        statistics; input of `lidarjax localize`), map.yaml + map.pgm (ROS map_server) and
        map.png.
        """,
        "lidarjax map intel -o out/intel --scans 0:910:2 --resolution 0.05\n"
        "  lidarjax map run.bag -o out/bag --topic /scan --model reflection",
        "_map:cmd_map",
    )
    p.add_argument("log", metavar="LOG", help="registry name, CARMEN log or ROS bag")
    p.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    p.add_argument(
        "--model",
        choices=("decay-rate", "reflection", "endpoint"),
        default="decay-rate",
        help="sensor model of the map",
    )
    p.add_argument("--resolution", type=float, default=0.05, metavar="M", help="cell size (m)")
    p.add_argument("--scans", metavar="START:STOP[:STEP]", help="scans to use (default: all)")
    p.add_argument("--topic", help="LaserScan topic of a ROS bag (default: the only one)")
    _azimuth_layout_option(p)
    p.add_argument(
        "--margin", type=float, default=1.0, metavar="M", help="grid margin around the data (m)"
    )
    p.add_argument(
        "--max-range",
        type=float,
        metavar="M",
        help="readings at or beyond this range are no-returns (default: the log's usable range)",
    )
    p.add_argument("--chunk", type=int, default=64, metavar="SCANS", help="scans traced per chunk")
    p.add_argument(
        "--sigma", type=float, default=0.1, metavar="M", help="endpoint model: hit std (m)"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    # ---------------------------------------------------------------- localize
    p = _sub(
        sub,
        "localize",
        "particle-filter localization in a map written by `lidarjax map`",
        """
        Track the robot of LOG through the map MAP (a map.npz written by `lidarjax map`)
        with the particle filter of lidarjax.localization: odometry motion model driven by
        the log's raw odometry, the scan likelihood of the map's sensor model on BEAMS
        evenly spaced beams, systematic resampling. The filter runs in chunks of steps
        (each continues from the state the previous one returned) with a progress bar.
        Writes trajectory.tum (TUM: t x y z qx qy qz qw) and trajectory_kitti.txt (KITTI
        3x4 poses), and, when the log has ground truth (the corrected poses of a CARMEN
        log, tf in a bag), errors.png (position and heading error over time) and
        errors.json, and prints the ATE (RMSE of the position error, no alignment).
        With several JAX devices (`lidarjax --host-devices N localize ...`, or GPUs) the
        particles are split over them when their count is a multiple of the device count
        (the same results, each device measuring its own particles).
        """,
        "lidarjax localize out/intel/map.npz intel -o out/loc --scans 1:400:2 --particles 500\n"
        "  lidarjax localize map.npz intel -o out/loc2 --init 1.2,-0.4,0.3",
        "_localize:cmd_localize",
    )
    p.add_argument("map", metavar="MAP", help="map.npz written by `lidarjax map`")
    p.add_argument("log", metavar="LOG", help="registry name, CARMEN log or ROS bag")
    p.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    p.add_argument("--particles", type=int, default=500, metavar="N", help="number of particles")
    p.add_argument("--scans", metavar="START:STOP[:STEP]", help="scans to track (default: all)")
    p.add_argument(
        "--init",
        default="gt",
        metavar="gt|odom|X,Y,THETA",
        help="initial pose: the first scan's ground truth, its raw odometry pose, or "
        "x,y,theta (m, m, rad) in the map frame",
    )
    p.add_argument(
        "--init-std", default="0.3,0.3,0.1", metavar="SX,SY,STH", help="initial spread (m, m, rad)"
    )
    p.add_argument("--beams", type=int, default=60, metavar="B", help="beams per scan used")
    p.add_argument("--seed", type=int, default=0, help="PRNG seed")
    p.add_argument("--topic", help="LaserScan topic of a ROS bag (default: the only one)")
    _azimuth_layout_option(p)
    p.add_argument("--chunk", type=int, default=32, metavar="STEPS", help="filter steps per chunk")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    # ---------------------------------------------------------------- slam
    p = _sub(
        sub,
        "slam",
        "decay-rate SLAM: trajectory and map from a laser log's scans and odometry",
        """
        Estimate the trajectory and the map of LOG from its scans and raw odometry with
        lidarjax.slam.run_slam: the online front end matches every scan against the
        decay-rate map of the --local-map-scans scans before it (coarse to fine, from
        the odometry's prediction), loop closures are searched against earlier visits,
        and a pose graph (and optionally a joint or alternating back end over all poses
        and the map) corrects the drift. Readings at or beyond --range-cap (default: the smallest of
        20, 30 and 40 m that keeps 98 % of the log's returns, at most the sensor's
        usable range) are no-returns. The shared CARMEN logs'
        odometry equals their corrected poses; --drift SEED simulates a drifting wheel
        odometry from them instead (the settings of configs/slam.yaml), as the SLAM
        experiment does. Writes into OUT: trajectory.tum (the estimate), front_end.tum,
        odometry.tum (TUM, time stamps in s, or scan indices where the log's are not
        increasing), loops.csv (loop closures and revisits: scan pairs, relative poses and
        their weights in the final pose graph, below 0.1 for one it rejected),
        front_end.csv (each match's rays, sds, gate flag, seconds and the graph's weights of
        its increments), map.npz (the decay-rate map at the estimate; input of `lidarjax localize`),
        map.yaml + map.pgm, slam.png and slam.json, and, where LOG has ground truth,
        errors.png and the errors (ATE after SE(2) alignment, RPE) in slam.json. The
        estimate is in the odometry's frame, starting at its first pose.
        """,
        "lidarjax slam intel -o out/slam --azimuth-layout sweep --drift 0\n"
        "  lidarjax slam run.bag -o out/slam-bag --topic /scan",
        "_slam:cmd_slam",
    )
    p.add_argument("log", metavar="LOG", help="registry name, CARMEN log or ROS bag")
    p.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    p.add_argument("--scans", metavar="START:STOP[:STEP]", help="scans to use (default: all)")
    p.add_argument("--topic", help="LaserScan topic of a ROS bag (default: the only one)")
    _azimuth_layout_option(p)
    p.add_argument(
        "--model",
        choices=("decay-rate", "endpoint"),
        default="decay-rate",
        help="scan-matching model of the front end and the loop search (endpoint: the "
        "likelihood-field baseline)",
    )
    p.add_argument(
        "--back-end",
        choices=("none", "joint", "alternating"),
        default="none",
        help="after the pose graph: none, the joint optimisation of all poses and the map, "
        "or the alternating scheme (both take minutes on a few hundred scans)",
    )
    p.add_argument(
        "--loop-rounds", type=int, default=2, metavar="N", help="rounds of loop search (>= 1)"
    )
    p.add_argument(
        "--range-cap",
        type=float,
        metavar="M",
        help="readings at or beyond this range are no-returns (default: the smallest of "
        "20, 30 and 40 m that keeps 98 %% of the selected scans' returns, at most the "
        "log's usable range: lidarjax.slam.auto_range_cap)",
    )
    p.add_argument("--resolution", type=float, default=0.05, metavar="M", help="cell size (m)")
    p.add_argument(
        "--odometry-noise",
        type=float,
        default=1.0,
        metavar="K",
        help="scales the odometry model (the front end's prior on each increment, also the "
        "weight of the pose graph's odometry factors: 0.02 m + 10 %% of the step, 0.01 "
        "rad + 0.03 rad/m + 5 %% of the turn, times K); raise it for a noisier odometry",
    )
    p.add_argument(
        "--grazing-cells",
        type=float,
        default=1.0,
        metavar="N",
        help="where a ray grazes a wall, its stretch within N cells of the wall is left "
        "out of the free space (the map's and the match's; 0: off; decay-rate model only)",
    )
    p.add_argument(
        "--local-map-scans",
        type=int,
        default=100,
        metavar="N",
        help="the front end matches each scan against the last N scans only, and the loop "
        "closures alone join revisits; 0: against every scan so far, with the front end's "
        "own revisits in the pose graph (default: 100)",
    )
    p.add_argument(
        "--extra-chains",
        default="auto",
        metavar="MODELS",
        help="further front ends whose increments join the pose graph as further robust "
        "chains: 'auto' (default: the other matching model, endpoint beside decay-rate "
        "and the reverse, and icp), 'none', or a comma-separated list of decay-rate, endpoint, "
        "icp (point-to-line ICP, built in), gicp (small_gicp's scan-to-submap "
        "registration); the rejected registrations of icp and gicp stay out of the "
        "graph; their trajectories are written as front_end_MODEL.tum",
    )
    p.add_argument(
        "--short-loops",
        type=int,
        default=0,
        metavar="N",
        help="after the loop rounds, match every scan against the submap of the nearest "
        "earlier scan at least N (>= 3) scans back along the pose graph and solve it again "
        "with the loop closures accepted (0, default: off; written as kind 'short' in "
        "loops.csv)",
    )
    p.add_argument(
        "--no-odometry-calibration",
        action="store_true",
        help="give the pose graph the raw odometry; by default its systematic heading "
        "errors (drift per metre, error per radian turned) are fitted against the front "
        "end and removed first (reported in slam.json)",
    )
    p.add_argument(
        "--drift",
        type=int,
        metavar="SEED",
        help="start from a simulated drifting wheel odometry (seed SEED) made from LOG's "
        "ground-truth poses instead of LOG's odometry",
    )
    p.add_argument(
        "--resimulate",
        type=int,
        metavar="SEED",
        help="replace LOG's scans by lidarjax.sim.resimulate_scans of them: LOG's own "
        "surfaces at its ground-truth poses, cast again from those poses (1 cm cells, 1 cm "
        "noise of seed SEED, no surface within 0.2 m of a pose), so the errors are against "
        "exact poses",
    )
    p.add_argument(
        "--rpe-delta",
        type=float,
        default=1.0,
        metavar="M",
        help="path length of the relative pose error (m)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bars")

    # ---------------------------------------------------------------- polylines
    p = _sub(
        sub,
        "polylines",
        "PLE / PLE+ polylines of one 2-D scan",
        """
        Extract the maximum-likelihood polylines of one scan of LOG with PLE (greedy vertex
        removal, Eq. 10.3) and optionally refine them with PLE+ (Eq. 10.4). The polylines
        are in the sensor frame (m). Writes polylines.csv (one vertex per row), polylines.svg
        (with the scan points), polylines.png and prints J, the RMSE and the explained rays.
        """,
        "lidarjax polylines intel -o out/pl --scan 633 --J 50 --plus",
        "_features:cmd_polylines",
    )
    p.add_argument("log", metavar="LOG", help="registry name, CARMEN log or ROS bag")
    p.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    p.add_argument("--scan", type=int, default=0, metavar="I", help="scan index")
    p.add_argument("--J", type=int, default=30, dest="J", help="maximum number of vertices")
    p.add_argument("--plus", action="store_true", help="refine with PLE+")
    p.add_argument("--topic", help="LaserScan topic of a ROS bag (default: the only one)")
    _azimuth_layout_option(p)

    # ---------------------------------------------------------------- planes
    p = _sub(
        sub,
        "planes",
        "PPE plane extraction from an organized point cloud",
        """
        Extract planes from an organized 3-D scan (sensor at the origin) with PPE, the
        maximum-likelihood plane extraction of chapter 11. CLOUD is a PCD or PLY file; an
        organized cloud (PCD HEIGHT > 1, or a PLY written by lidarjax) keeps its rows. An
        unorganized cloud needs --shape H W (its points in row-major scan order) or
        --organise SENSOR (a spinning lidar's cloud in its sensor frame, put into beams x
        azimuth columns with the sensor's nominal beam layout, or its `ring` field). NaN
        points are no-returns. Writes the cloud with a label per point (labelled.pcd or
        labelled.ply; label 0: no plane, plane j: j + 1), planes.png (label image and top
        view) and planes.json (per plane: points, normal, distance, error), and prints a
        summary.
        """,
        "lidarjax planes ../shared/data/synpeb/test_100.pcd -o out/planes --max-distance 0.2\n"
        "lidarjax planes velodyne.ply -o out/planes2 --organise hdl64e --columns 2048",
        "_features:cmd_planes",
    )
    p.add_argument("cloud", metavar="CLOUD", help="PCD or PLY file")
    p.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    p.add_argument("--shape", type=int, nargs=2, metavar=("H", "W"), help="rows and columns")
    p.add_argument(
        "--organise",
        choices=("hdl64e", "hdl32e", "vlp16"),
        metavar="SENSOR",
        help="organise a spinning-lidar cloud with this beam layout: hdl64e, hdl32e, vlp16",
    )
    p.add_argument(
        "--columns", type=int, default=1024, metavar="W", help="--organise: columns per turn"
    )
    p.add_argument(
        "--max-distance",
        type=float,
        default=0.2,
        metavar="M",
        help="neighbours farther apart than this are never in one plane (m)",
    )
    p.add_argument(
        "--min-points", type=int, default=30, metavar="N", help="smallest plane reported"
    )

    # ---------------------------------------------------------------- poles
    p = _sub(
        sub,
        "poles",
        "pole extraction from a 3-D point cloud or a simulated urban drive",
        """
        Extract poles (ch. 12): rays are traced into a 3-D voxel grid (hits and misses),
        turned into the occupancy of the full-posterior reflection map and scored for
        vertical, free-standing columns. SOURCE is either
          sim                 a simulated urban drive along the registered KITTI-00
                              trajectory (lidarjax.sim; --scans picks its poses): the
                              extracted poles are compared with the simulator's true ones;
          CLOUD.pcd|.ply      one registered scan, x y z in metres with z up, taken from
                              --sensor X,Y,Z: every point is the end of a ray from there
                              (a cloud has no no-return rays, so free space is only known
                              along the rays that hit something).
        The local map is PoleConfig's 30 x 30 x 5 m grid (0.2 m voxels) around the sensor.
        Writes poles.csv (x, y, width, score, z range), poles.png and poles.json.
        """,
        "lidarjax poles sim -o out/poles --scans 40:42\n"
        "  lidarjax poles scan.pcd -o out/poles --sensor 0,0,1.73",
        "_features:cmd_poles",
    )
    p.add_argument("source", metavar="SOURCE", help="`sim`, or a PCD / PLY point cloud")
    p.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    p.add_argument(
        "--scans", default="40:42", metavar="START:STOP[:STEP]", help="sim: poses of the drive"
    )
    p.add_argument("--seed", type=int, default=0, help="sim: world and noise seed")
    p.add_argument(
        "--azimuths", type=int, default=1080, metavar="N", help="sim: azimuths per lidar turn"
    )
    p.add_argument("--sensor", default="0,0,0", metavar="X,Y,Z", help="cloud: sensor position (m)")
    p.add_argument("--ground-z", type=float, default=0.0, metavar="M", help="cloud: ground height")

    # ---------------------------------------------------------------- experiment
    p = _sub(
        sub,
        "experiment",
        "run a packaged Hydra experiment",
        """
        Run one of the packaged experiments (experiments/<NAME>.py with configs/<NAME>.yaml)
        in a new Python process. Everything after NAME is passed on as Hydra overrides.
        Outputs go where the config says, relative to the current folder (outputs/<NAME>/ by
        default; override with hydra.run.dir=...). `--list` names them.
        """,
        "lidarjax experiment demo localization.particles=1000 grid.resolution_m=0.05\n"
        "  lidarjax experiment mcl logs=[intel] filter.runs=2 filter.max_steps=20",
        "_experiment:cmd_experiment",
    )
    p.add_argument("name", nargs="?", metavar="NAME", help="experiment name (see --list)")
    p.add_argument(
        "overrides", nargs=argparse.REMAINDER, metavar="OVERRIDE", help="Hydra overrides"
    )
    p.add_argument("--list", action="store_true", help="list the experiments and exit")
    return parser


def _host_devices(n: int | None) -> None:
    """Expose ``n`` CPU devices (``--host-devices``, else ``$LIDARJAX_HOST_DEVICES``)
    before the subcommand imports JAX (:func:`lidarjax.distributed.use_host_devices`); a
    bad value is an input error naming its source."""
    from ..distributed import host_devices_from_env, use_host_devices

    argument = "--host-devices"
    if n is None:
        argument = f"${HOST_DEVICES_ENV}"
        try:
            n = host_devices_from_env()
        except ValueError as e:
            raise CliInputError(argument, str(e).removeprefix(f"{argument} ")) from None
        if n is None:
            return
    if n < 1:
        raise CliInputError(argument, f"must be >= 1, got {n}")
    try:
        use_host_devices(n)
    except RuntimeError as e:
        raise CliInputError(argument, str(e)) from None
    os.environ[HOST_DEVICES_ENV] = str(n)  # `lidarjax experiment`'s process: the same count


def _error(command: str | None, message: str) -> None:
    where = f"{PROG} {command}" if command else PROG
    print(f"{where}: error: {message}", file=sys.stderr)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``lidarjax`` command line.

    Args:
        argv: the arguments (default ``sys.argv[1:]``).

    Returns:
        The exit status: 0 on success, 2 for bad input (usage errors, a missing or corrupt
        file: one line naming the argument), 1 for any other failure (one line; ``--debug``
        shows the traceback), 130 when interrupted.
    """
    parser = build_parser()
    try:
        args = parser.parse_args(list(sys.argv[1:] if argv is None else argv))
    except SystemExit as e:  # --help, --version and usage errors
        return int(e.code or 0) if not isinstance(e.code, str) else 2
    module, func = args.handler.split(":")
    try:
        _host_devices(args.host_devices)
        if args.x64:
            import jax

            jax.config.update("jax_enable_x64", True)
        handler = getattr(importlib.import_module(f"{__package__}.{module}"), func)
        return int(handler(args) or 0)
    except CliInputError as e:
        if args.debug:
            raise
        _error(args.command, str(e))
        return 2
    except KeyboardInterrupt:
        if args.debug:
            raise
        _error(args.command, "interrupted")
        return 130
    except Exception as e:  # anything else: one line, the traceback with --debug
        if args.debug:
            raise
        msg = " ".join(str(e).split())
        _error(args.command, f"{type(e).__name__}: {msg} (run with --debug for the traceback)")
        return 1
