"""A picture of what the live view streams: a result file's windows served by labrig's view server, received by
the headless client, decoded from their CDR and drawn with matplotlib (not Foxglove's own window: the same
messages, as its 3D, image and plot panels get them).

    python tools/view_snapshot.py RESULT.h5 docs/images/view-server.png

RESULT.h5: ``labrig run REC --out RESULT.h5 --out-depth``. The windows are served at their own pace (the
windows' span apart); the frame drawn is the one with the largest net normal force.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from labrig.live.view_server import ViewServer
from labrig.pipeline.results import load_result
from labrig.pipeline.ros2_messages import point_cloud_columns
from labrig.pipeline.runtime import WindowResult
from labrig.recording.ros2 import messages as M
from labrig.recording.ros2 import topics
from labrig.testing.foxglove_client import FoxgloveClient


def serve(result: Path) -> FoxgloveClient:
    data = load_result(result)
    n = data["t1_us"].shape[0]
    span_s = float(np.median(data["t1_us"] - data["t0_us"])) / 1e6
    with ViewServer(data["rest_mm"], port=0) as server, FoxgloveClient(server.url, keep_payloads=True) as client:
        start = time.monotonic()
        for i in range(n):
            server.publish(WindowResult(i, int(data["t0_us"][i]), int(data["t1_us"][i]), int(data["n_events"][i]),
                                        data["positions_px"][i], data["updated"][i].astype(bool),
                                        data["displacement_mm"][i], data["forces_n"][i], data["net_force_n"][i],
                                        data["contact_px"][i], data["contact_mm"][i], data["depth_mm"][i]))
            time.sleep(max(0.0, start + (i + 1) * span_s - time.monotonic()))
        time.sleep(0.5)
    return client


def draw(client: FoxgloveClient, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    store = M.typestore()
    nets = [store.deserialize_cdr(p, M.WRENCH_STAMPED) for p in client.topics[topics.NET_FORCE].payloads]
    fz = np.array([w.wrench.force.z for w in nets])
    t_s = (np.array(client.topics[topics.NET_FORCE].log_times_ns) - client.topics[topics.NET_FORCE].log_times_ns[0]) / 1e9
    k = int(np.argmin(fz))
    field = point_cloud_columns(store.deserialize_cdr(client.topics[topics.FORCE_FIELD].payloads[k], M.POINT_CLOUD2))
    depth = store.deserialize_cdr(client.topics[topics.DEPTH].payloads[k], M.IMAGE)
    tracks = point_cloud_columns(store.deserialize_cdr(client.topics[topics.TRACKS].payloads[k], M.POINT_CLOUD2))
    fig, axes = plt.subplots(1, 4, figsize=(17, 4.2))
    x, y = field["x"] * 1000, field["y"] * 1000
    sc = axes[0].scatter(x, y, c=field["fz"], cmap="viridis", s=22)
    axes[0].quiver(x, y, field["fx"], field["fy"], color="tab:red", scale=None)
    axes[0].set(title=f"{topics.FORCE_FIELD} (PointCloud2)", xlabel="x, gel frame (mm)", ylabel="y (mm)", aspect="equal")
    fig.colorbar(sc, ax=axes[0], label="fz on the gel (N)")
    image = np.asarray(depth.data, np.uint8).view("<f4").reshape(depth.height, depth.width)
    im = axes[1].imshow(image, cmap="magma")
    axes[1].set(title=f"{topics.DEPTH} (Image 32FC1)")
    fig.colorbar(im, ax=axes[1], label="depth (mm)")
    moved = tracks["updated"] > 0
    axes[2].scatter(tracks["u"][~moved], tracks["v"][~moved], s=8, c="0.6", label="kept")
    axes[2].scatter(tracks["u"][moved], tracks["v"][moved], s=8, c="tab:blue", label="updated")
    axes[2].invert_yaxis()
    axes[2].set(title=f"{topics.TRACKS} (PointCloud2)", xlabel="u (px)", ylabel="v (px)", aspect="equal")
    axes[2].legend(loc="lower right", fontsize=8)
    axes[3].plot(t_s, fz, lw=1)
    axes[3].axvline(t_s[k], color="0.5", lw=0.8)
    axes[3].set(title=f"{topics.NET_FORCE} (WrenchStamped)", xlabel="receive time (s)", ylabel="net Fz on the gel (N)")
    fig.suptitle(f"labrig run --live --view-server, as a client receives it: {len(nets)} windows, frame {k} drawn "
                 "(matplotlib rendering of the decoded messages)", fontsize=10)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("result", type=Path, help="labrig run --out RESULT.h5 --out-depth")
    ap.add_argument("out", type=Path, help="PNG to write")
    args = ap.parse_args()
    draw(serve(args.result), args.out)
    print(args.out)


if __name__ == "__main__":
    main()
