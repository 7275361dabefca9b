"""A real S3-compatible HTTP server on loopback for tests: moto's ThreadedMotoServer.

Import the fixtures into a test module (``from tests.s3server import s3_server, s3_store``) or use
:class:`S3Server` directly when a test needs to stop and restart the server (fault tests).
"""
from __future__ import annotations

import os
import uuid

import pytest


class S3Server:
    """moto in server mode on 127.0.0.1, an OS-chosen port, in a thread of this process.

    moto keeps its state in process memory, so a server restarted with :meth:`restart` (a new
    port) still has the buckets and objects written before :meth:`stop`.
    """

    def __init__(self):
        self._server = None
        self.endpoint_url: str | None = None

    def start(self) -> "S3Server":
        import logging

        from moto.server import ThreadedMotoServer

        logging.getLogger("werkzeug").setLevel(logging.ERROR)  # one log line per request otherwise

        # Dummy credentials for the local server; never real ones.
        os.environ.setdefault("AWS_ACCESS_KEY_ID", "testing")
        os.environ.setdefault("AWS_SECRET_ACCESS_KEY", "testing")
        os.environ.setdefault("AWS_DEFAULT_REGION", "us-east-1")
        self._server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
        self._server.start()
        host, port = self._server.get_host_and_port()
        self.endpoint_url = f"http://{host}:{port}"
        return self

    def stop(self) -> None:
        if self._server is not None:
            self._server.stop()
            self._server = None

    def restart(self) -> "S3Server":
        self.stop()
        return self.start()

    def storage_options(self, *, fail_fast: bool = False) -> dict:
        """s3fs options for this server (no region in client_kwargs: moto's mkdir fails with one).

        ``fail_fast`` turns off retries so a stopped server fails a request within a second.
        """
        opts: dict = {"client_kwargs": {"endpoint_url": self.endpoint_url}, "skip_instance_cache": True}
        if fail_fast:
            opts["config_kwargs"] = {"retries": {"max_attempts": 1}, "connect_timeout": 1, "read_timeout": 2}
        return opts

    def new_bucket(self) -> str:
        import boto3

        name = f"rel-{uuid.uuid4().hex[:12]}"
        boto3.client("s3", endpoint_url=self.endpoint_url, region_name="us-east-1").create_bucket(Bucket=name)
        return name

    def client(self):
        import boto3

        return boto3.client("s3", endpoint_url=self.endpoint_url, region_name="us-east-1")


@pytest.fixture(scope="module")
def s3_server():
    server = S3Server().start()
    yield server
    server.stop()


@pytest.fixture
def s3_store(s3_server):
    """``(store URL, storage_options)`` of a fresh bucket on the module's S3 server."""
    bucket = s3_server.new_bucket()
    return f"s3://{bucket}/releases", s3_server.storage_options()
