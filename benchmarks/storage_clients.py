"""S3 client benchmark: boto3 against obstore on what bonemesh's storage does, against a real S3 store.

    python -m benchmarks.storage_clients [--sizes-mib 64,256] [--repeat 3] [--outputs 8] [--output-mib 4]
                                          [--signs 400] --out result.json

It starts SeaweedFS (``weed server -s3``, ``tests/service/seaweed.py``) on loopback and times, per client:

- ``upload``: a scan streamed in as the API receives it (4 MiB batches handed over one by one, never whole in
  memory) into one multipart upload of 8 MiB parts, completed at the end (boto3: ``core.s3storage``'s writer, 4
  parts in flight; obstore: ``open_writer``, its default 12 in flight);
- ``download``: the object streamed back into a local file (the worker's scratch copy);
- ``publish``: ``--outputs`` files of ``--output-mib`` put one after another (a job's outputs);
- ``sign``: ``--signs`` presigned GET links (a job listing of 50 jobs x 8 outputs is 400);
- ``client``: making a client (each worker and API process does it once).

Each is the median of ``--repeat`` runs, in seconds; throughput in MiB/s. Both clients run in the same process
against the same server, alternating which goes first.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import os
import platform
import statistics
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from benchmarks.report import stop_on_sigterm, write_json
from tests.service.seaweed import REGION, SeaweedServer

BATCH = 4 << 20
PART = 8 << 20


class Boto3Client:
    name = "boto3"

    def __init__(self, s3: SeaweedServer, bucket: str) -> None:
        from core.s3storage import make_client

        self.client, self.bucket = make_client(s3.endpoint), bucket  # the client bonemesh makes

    def upload(self, key: str, batches: Callable[[], Any]) -> None:
        from core.s3storage import _S3Upload  # what the API ships: 8 MiB parts, 4 in flight

        writer = _S3Upload(self.client, self.bucket, key, 1 << 40)
        for batch in batches():
            writer.write(batch)
        writer.commit()

    def download(self, key: str, dest: Path) -> None:
        self.client.download_file(self.bucket, key, str(dest))

    def put(self, key: str, path: Path) -> None:
        with open(path, "rb") as fh:
            self.client.put_object(Bucket=self.bucket, Key=key, Body=fh, ContentType="model/stl")

    def sign(self, key: str) -> str:
        return str(
            self.client.generate_presigned_url("get_object", Params={"Bucket": self.bucket, "Key": key}, ExpiresIn=3600)
        )


class ObstoreClient:
    name = "obstore"

    def __init__(self, s3: SeaweedServer, bucket: str) -> None:
        from obstore.store import S3Store

        self.store = S3Store(
            bucket,
            endpoint=s3.endpoint,
            access_key_id=s3.access_key,
            secret_access_key=s3.secret_key,
            region=REGION,
            virtual_hosted_style_request=False,
            client_options={"allow_http": True},
        )

    def upload(self, key: str, batches: Callable[[], Any]) -> None:
        import obstore

        with obstore.open_writer(self.store, key, buffer_size=PART) as out:
            for batch in batches():
                out.write(batch)

    def download(self, key: str, dest: Path) -> None:
        import obstore

        with open(dest, "wb") as fh:
            for chunk in obstore.get(self.store, key).stream(min_chunk_size=PART):
                fh.write(chunk)

    def put(self, key: str, path: Path) -> None:
        import obstore

        obstore.put(self.store, key, path, attributes={"Content-Type": "model/stl"})

    def sign(self, key: str) -> str:
        import obstore

        return str(obstore.sign(self.store, "GET", key, dt.timedelta(seconds=3600)))


CLIENTS = {"boto3": Boto3Client, "obstore": ObstoreClient}


def timed(fn: Callable[[], Any]) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def one_round(client: Any, size: int, work: Path, args: argparse.Namespace) -> dict[str, float]:
    chunk = os.urandom(BATCH)

    def batches() -> Any:
        left = size
        while left > 0:
            yield memoryview(chunk)[: min(BATCH, left)]
            left -= BATCH

    key = f"bench/{client.name}/{os.urandom(4).hex()}"
    out: dict[str, float] = {"upload_s": timed(lambda: client.upload(key, batches))}
    dest = work / f"{client.name}.bin"
    out["download_s"] = timed(lambda: client.download(key, dest))
    if dest.stat().st_size != size:
        raise RuntimeError(f"{client.name}: downloaded {dest.stat().st_size} bytes of {size}")
    dest.unlink()
    part = work / "output.bin"
    part.write_bytes(os.urandom(args.output_mib << 20))
    out["publish_s"] = timed(lambda: [client.put(f"{key}-out/{i}", part) for i in range(args.outputs)])
    out["sign_s"] = timed(lambda: [client.sign(f"{key}-out/{i % args.outputs}") for i in range(args.signs)])
    return out


def measure(s3: SeaweedServer, args: argparse.Namespace, work: Path) -> list[dict[str, Any]]:
    bucket = s3.make_bucket()
    results = []
    for mib in args.sizes_mib:
        runs: dict[str, list[dict[str, float]]] = {name: [] for name in CLIENTS}
        made: dict[str, list[float]] = {name: [] for name in CLIENTS}
        for r in range(args.repeat):
            order = list(CLIENTS) if r % 2 == 0 else list(reversed(CLIENTS))
            for name in order:
                t0 = time.perf_counter()
                client = CLIENTS[name](s3, bucket)
                made[name].append(time.perf_counter() - t0)
                runs[name].append(one_round(client, mib << 20, work, args))
        for name in CLIENTS:
            med = {k: statistics.median(run[k] for run in runs[name]) for k in runs[name][0]}
            results.append(
                {
                    "client": name,
                    "size_mib": mib,
                    **med,
                    "client_s": statistics.median(made[name]),
                    "upload_mib_s": mib / med["upload_s"],
                    "download_mib_s": mib / med["download_s"],
                    "sign_us_each": 1e6 * med["sign_s"] / args.signs,
                }
            )
    return results


@contextlib.contextmanager
def _keys(s3: SeaweedServer) -> Iterator[None]:
    """The server's keys in the environment, where boto3's credential chain reads them."""
    saved = {k: os.environ.get(k) for k in s3.env("x")}
    os.environ.update({k: v for k, v in s3.env("x").items() if k.startswith("AWS_")})
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes-mib", type=lambda s: [int(x) for x in s.split(",")], default=[64, 256])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--outputs", type=int, default=8)
    parser.add_argument("--output-mib", type=int, default=4)
    parser.add_argument("--signs", type=int, default=400)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    stop_on_sigterm()
    import boto3
    import obstore

    load_before = os.getloadavg()
    with SeaweedServer() as s3, _keys(s3), tempfile.TemporaryDirectory(prefix="bonemesh-s3bench-") as tmp:
        results = measure(s3, args, Path(tmp))
    load = {"before": load_before, "after": os.getloadavg()}  # other work on the machine skews the numbers
    report = {
        "benchmark": "storage_clients",
        "store": "SeaweedFS (weed server -s3) on loopback",
        "versions": {"boto3": boto3.__version__, "obstore": obstore.__version__},
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "load_average_1_5_15": load},
        "args": {k: v for k, v in vars(args).items() if k != "out"},
        "results": results,
    }
    write_json(args.out, report)
    for r in results:
        print(
            f"{r['client']:8s} {r['size_mib']:5d} MiB  upload {r['upload_mib_s']:7.1f} MiB/s  download "
            f"{r['download_mib_s']:7.1f} MiB/s  publish {r['publish_s']:.3f} s  sign {r['sign_us_each']:.0f} us  "
            f"client {r['client_s'] * 1e3:.1f} ms"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
