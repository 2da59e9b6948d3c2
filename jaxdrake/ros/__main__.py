"""The ROS–LCM translator: carry LCM channels to ROS topics and back (notes, D.5.2).

    python -m jaxdrake.ros [--map FILE.toml] [--to-ros CHANNEL TOPIC TYPE LCM ...]
        [--to-lcm TOPIC CHANNEL TYPE LCM ...] [--url LCM_URL] [--ros {1,2}] [--domain-id N]
        [--dds {loopback,environment}] [--master-timeout S] [--duration S] [--record BAG]
    python -m jaxdrake.ros --convert LCM_LOG --record BAG [--map FILE.toml | routes]

TYPE is std_msgs/Float64MultiArray, sensor_msgs/JointState, geometry_msgs/Twist or
geometry_msgs/WrenchStamped. LCM names the LCM side: signal=A,B (lcmt_drake_signal with those
coordinates), robot_state=J1,J2, robot_command=J1,J2, or state_of= / input_of= / output_of=
module:system (that port of a jaxdrake system). Example, the pendulum's state to ROS 1:

    python -m jaxdrake.ros --url tcpq://127.0.0.1:7700 \\
        --to-ros PendulumState /pendulum/state sensor_msgs/JointState state_of=jaxdrake.models:Pendulum

ROS 1 uses ROS_MASTER_URI (set ROS_IP / ROS_HOSTNAME=127.0.0.1 to stay on this host); a master
gone for --master-timeout seconds (default 30) ends the translator with exit code 3; one that
returns sooner gets the translator's topics registered again. ROS 2 joins DDS domain
--domain-id on the loopback interface only (--dds environment: Cyclone's own configuration,
CYCLONEDDS_URI). --record writes what the translator carries to a bag (a .bag path: ROS 1;
otherwise a ROS 2 MCAP bag folder); --convert writes an LCM event log's messages to one.
SIGINT / SIGTERM stop it cleanly; it then prints each route's counters. Exit codes: 0 stopped,
2 bad arguments or mapping, 3 ROS master unreachable, 4 ROS packages missing.
"""

import argparse
import logging
import sys


def routes_from(args, parser):
    from ._routes import TO_LCM, TO_ROS, Route, check_routes, read_mapping

    routes, url = [], None
    try:
        if args.map:
            routes, url = read_mapping(args.map)
        for channel, topic, type_name, lcm in args.to_ros or []:
            routes.append(Route.parse(TO_ROS, channel, topic, type_name, lcm))
        for topic, channel, type_name, lcm in args.to_lcm or []:
            routes.append(Route.parse(TO_LCM, channel, topic, type_name, lcm))
        return check_routes(routes), url
    except (ValueError, OSError) as error:
        parser.error(str(error))


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m jaxdrake.ros", description=__doc__.splitlines()[0],
                                     epilog="\n".join(__doc__.splitlines()[2:]),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--map", help="TOML mapping file ([[route]] tables, optional lcm_url)")
    parser.add_argument("--to-ros", nargs=4, action="append", metavar=("CHANNEL", "TOPIC", "TYPE", "LCM"),
                        help="carry LCM channel CHANNEL to ROS topic TOPIC as TYPE, decoded as LCM says "
                             "(repeatable; TYPE and LCM below)")
    parser.add_argument("--to-lcm", nargs=4, action="append", metavar=("TOPIC", "CHANNEL", "TYPE", "LCM"),
                        help="carry ROS topic TOPIC of TYPE to LCM channel CHANNEL, encoded as LCM says "
                             "(repeatable)")
    parser.add_argument("--url", help="LCM URL (default: the mapping's lcm_url, else the multicast group "
                                      "with ttl=0, host only)")
    parser.add_argument("--ros", choices=("1", "2"), default="1", help="ROS 1 (rospy, default) or ROS 2 (DDS)")
    parser.add_argument("--domain-id", type=int, default=0, help="ROS 2: the DDS domain (ROS_DOMAIN_ID)")
    parser.add_argument("--dds", choices=("loopback", "environment"), default="loopback",
                        help="ROS 2: loopback only (default), or Cyclone's configuration from CYCLONEDDS_URI")
    parser.add_argument("--node-name", default="jaxdrake_ros", help="ROS 1 node name (a unique suffix is added)")
    parser.add_argument("--master-timeout", type=float, default=30.0,
                        help="ROS 1: seconds to wait for an absent master before exiting with code 3")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    parser.add_argument("--record", help="write the ROS side's messages to this bag (.bag: ROS 1, else ROS 2 MCAP)")
    parser.add_argument("--convert", metavar="LCM_LOG", help="write this LCM event log to --record's bag and exit")
    args = parser.parse_args(argv)
    routes, mapped_url = routes_from(args, parser)
    # the translator's own messages on stderr at INFO, whatever rospy does to the root logger
    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter("%(asctime)s %(name)s: %(message)s"))
    ours = logging.getLogger("jaxdrake")
    ours.addHandler(handler)
    ours.setLevel(logging.INFO)
    ours.propagate = False

    from ..lcm import HOST_ONLY_URL
    from ._bags import lcm_log_to_bag
    from ._ros1 import MasterError, Ros1Network, RosUnavailableError
    from ._translator import Translator

    if args.convert:
        if not args.record:
            parser.error("--convert needs --record BAG")
        counts = lcm_log_to_bag(args.convert, args.record, routes)
        print(f"wrote {args.record}: " + ", ".join(f"{k} {v}" for k, v in counts.items()), flush=True)
        return 0
    url = args.url or mapped_url or HOST_ONLY_URL
    try:
        if args.ros == "1":
            network = Ros1Network(args.node_name, master_timeout=args.master_timeout)
            where = f"ROS 1 master {network.master_uri}"
        else:
            from ._ros2 import LOOPBACK, Ros2Network

            network = Ros2Network(args.domain_id, config=LOOPBACK if args.dds == "loopback" else None)
            where = f"ROS 2 domain {args.domain_id} ({args.dds})"
        translator = Translator(routes, url, network=network, bag=args.record)
    except RosUnavailableError as error:
        print(f"error: RosUnavailableError: {error}", file=sys.stderr, flush=True)
        return 4
    except MasterError as error:
        print(f"error: MasterError: {error}", file=sys.stderr, flush=True)
        return 3
    print(f"translator between LCM {url} and {where}: " + "; ".join(map(str, routes)), flush=True)
    code = 0
    try:
        translator.run(args.duration)
    except MasterError as error:
        print(f"error: MasterError: {error}", file=sys.stderr, flush=True)
        code = 3
    finally:
        translator.close()
    for route, stats in translator.stats.items():
        print(f"stopped: {route}: {stats}", flush=True)
    return code


if __name__ == "__main__":
    sys.exit(main())
