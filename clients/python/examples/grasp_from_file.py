"""Plan a grasp from one depth view stored in a file, with nothing but the client installed.

    python grasp_from_file.py [--url http://127.0.0.1:8000] [--view tabletop_view.npz]

The file holds what a robot has after one camera frame: ``depth_mm`` (uint16 millimetres, as a
ROS ``16UC1`` image), ``mask`` (the object's pixels), ``K`` (3×3 camera matrix),
``camera_to_world`` (4×4) and the table as ``support_plane`` [nx, ny, nz, d] in the world frame.
Prints the best grasp's pre-grasp pose and joints; exits 1 when no grasp held.
"""

import argparse
import pathlib
import sys

import numpy as np

from grasp_client import GraspClient


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--url", default="http://127.0.0.1:8000",
                        help="the service (default: %(default)s)")
    parser.add_argument("--token", default=None, help="the service's GRASP_TOKEN (default: none)")
    parser.add_argument("--view", default=pathlib.Path(__file__).with_name("tabletop_view.npz"),
                        help="the stored view (default: tabletop_view.npz beside this script)")
    args = parser.parse_args()
    view = np.load(args.view)
    with GraspClient(args.url, token=args.token) as client, \
            client.session(support_plane=view["support_plane"]) as session:
        answer = session.add_view(view["depth_mm"], view["K"], mask=view["mask"],
                                  camera_pose=view["camera_to_world"], encoding="16UC1")
        grasps = session.grasps(top_k=1)
        if not grasps:
            print(f"no grasp held: {session.last_reason}")
            return 1
        best = grasps[0]
        print(f"view {answer['view_index']}: {answer['occupied_voxels']} voxels completed")
        print("pre-grasp pose (palm→world):")
        print(np.array2string(best.pregrasp_pose_world, precision=4, suppress_small=True))
        print("joints (deg):", {name: round(v, 1) for name, v in best.joints.items()})
        print(f"approach_stop={best.approach_stop} hold_probability={best.hold_probability}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
