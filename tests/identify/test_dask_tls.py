"""``qube-identify --scheduler tls://``: a cluster only holders of its CA's certificates can use.

A scheduler and a worker on 127.0.0.1 require TLS with certificates this test's own CA signed
(made in the test's folder): a fit through ``qube-identify --scheduler tls://... --tls-ca-file
--tls-cert --tls-key`` runs its statistics on the worker and says TLS in report.json, while a
client with no certificate, with another CA's, or over plain tcp:// is refused. Then, without a
cluster: a plain tcp:// address off the loopback is refused unless ``--insecure-scheduler``,
and each bad certificate option is a one-line error naming it.

The real cluster of processes (``dask scheduler``, ``dask worker``) is tests/identify/test_dask_cluster.py's;
the fit here runs on its logs (the ``cluster_logs`` fixture, tests/_cluster_logs.py) and helpers.
"""

from __future__ import annotations

import datetime
import gc
import ipaddress
import shutil
import socket
import ssl
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
from _cluster_logs import N_TRAIN

pytest.importorskip("dask.distributed", reason="the dask extra is optional")

from test_dask_cluster import _argv, _identify, _results

REFUSED = 10.0  # s: a refused client must fail well before this (it is told at once, not left to time out)


@dataclass(frozen=True)
class Certificates:
    """A CA's certificate, and one certificate and private key it signed (PEM files)."""

    ca: Path
    cert: Path
    key: Path

    def options(self) -> list[str]:
        """``qube-identify``'s options that present them."""
        return ["--tls-ca-file", str(self.ca), "--tls-cert", str(self.cert), "--tls-key", str(self.key)]

    def security(self, *roles: str):
        """A ``distributed.security.Security`` showing them in ``roles`` (client, scheduler, worker; default client)."""
        from distributed.security import Security

        files = {}
        for role in roles or ("client",):
            files.update({f"tls_{role}_cert": str(self.cert), f"tls_{role}_key": str(self.key)})
        return Security(tls_ca_file=str(self.ca), require_encryption=True, **files)


def _tool() -> str:
    """What makes certificates here: the cryptography package, else the openssl command (else skip)."""
    try:
        import cryptography  # noqa: F401
    except ImportError:
        if shutil.which("openssl") is None:
            pytest.skip("neither the cryptography package nor the openssl command to make certificates")
        return "openssl"
    return "cryptography"


def make_certificates(folder: Path, names: list[str], tool: str | None = None) -> dict[str, Certificates]:
    """A new CA in ``folder`` and, for each of ``names``, a certificate (for 127.0.0.1 and localhost) it signed."""
    folder.mkdir(parents=True)
    make = _with_openssl if (tool or _tool()) == "openssl" else _with_cryptography
    return make(folder, names)


def _with_cryptography(folder: Path, names: list[str]) -> dict[str, Certificates]:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    now = datetime.datetime.now(datetime.UTC)

    def write(path: Path, cert, key=None) -> Path:
        path.write_bytes(
            cert.public_bytes(serialization.Encoding.PEM)
            if key is None
            else key.private_bytes(
                serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
            )
        )
        return path

    def named(name: str) -> x509.Name:
        return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])

    def signed(subject: str, key, issuer: str, signer, ca: bool):
        builder = (
            x509.CertificateBuilder()
            .subject_name(named(subject))
            .issuer_name(named(issuer))
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=1))
            .add_extension(x509.BasicConstraints(ca=ca, path_length=0 if ca else None), critical=True)
        )
        if not ca:
            builder = builder.add_extension(
                x509.SubjectAlternativeName(
                    [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
                ),
                critical=False,
            )
        return builder.sign(signer, hashes.SHA256())

    ca_key, ca_name = ec.generate_private_key(ec.SECP256R1()), f"{folder.name} CA"
    ca = write(folder / "ca.pem", signed(ca_name, ca_key, ca_name, ca_key, True))
    made = {}
    for name in names:
        key = ec.generate_private_key(ec.SECP256R1())
        made[name] = Certificates(
            ca,
            write(folder / f"{name}.pem", signed(name, key, ca_name, ca_key, False)),
            write(folder / f"{name}-key.pem", None, key),
        )
    return made


def _with_openssl(folder: Path, names: list[str]) -> dict[str, Certificates]:
    """The commands of the TLS section of docs/cluster.md, with EC keys (faster to make)."""

    def openssl(*argv: str) -> None:
        subprocess.run(["openssl", *argv], cwd=folder, check=True, capture_output=True, timeout=60)

    key = ("-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes")
    openssl(
        "req", "-x509", *key, "-keyout", "ca-key.pem", "-out", "ca.pem", "-days", "1", "-subj", f"/CN={folder.name} CA"
    )
    (folder / "names.ext").write_text("subjectAltName = IP:127.0.0.1, DNS:localhost\n")
    made = {}
    for name in names:
        openssl("req", *key, "-keyout", f"{name}-key.pem", "-out", f"{name}.csr", "-subj", f"/CN={name}")
        openssl(
            "x509",
            "-req",
            "-in",
            f"{name}.csr",
            "-CA",
            "ca.pem",
            "-CAkey",
            "ca-key.pem",
            "-CAcreateserial",
            "-days",
            "1",
            "-extfile",
            "names.ext",
            "-out",
            f"{name}.pem",
        )
        made[name] = Certificates(folder / "ca.pem", folder / f"{name}.pem", folder / f"{name}-key.pem")
    return made


@pytest.fixture(scope="module")
def certificates(tmp_path_factory) -> dict[str, Certificates]:
    """The cluster's CA: the cluster's certificate (scheduler and worker) and a client's; a stranger CA's client."""
    root = tmp_path_factory.mktemp("tls")
    made = make_certificates(root / "cluster", ["node", "client"])
    return {**made, "stranger": make_certificates(root / "stranger", ["client"])["client"]}


@pytest.fixture
def tls_cluster(certificates):
    """A scheduler and a single-threaded worker on 127.0.0.1 that speak TLS only, with the cluster's CA."""
    from distributed import LocalCluster

    security = certificates["node"].security("scheduler", "worker", "client")  # the cluster's own client too
    with LocalCluster(
        protocol="tls",
        host="127.0.0.1",
        security=security,
        n_workers=1,
        threads_per_worker=1,
        processes=False,
        dashboard_address="127.0.0.1:0",
    ) as cluster:  # no fixed port
        yield cluster


@pytest.mark.dataset
def test_a_fit_runs_on_a_tls_cluster_that_refuses_clients_without_its_certificates(
    tls_cluster, certificates, cluster_logs, tmp_path
):
    from distributed import Client

    address = tls_cluster.scheduler_address
    assert address.startswith("tls://127.0.0.1:")
    with Client(address, security=certificates["client"].security(), set_as_default=False, timeout=30) as client:
        executed = lambda: sum(client.run(lambda dask_worker: dask_worker.state.executed_count).values())
        before = executed()
        _identify(
            _argv(
                cluster_logs,
                tmp_path / "fit",
                "--poly",
                "1",
                "--delays",
                "2",
                "--alpha",
                "1e-3",
                "--scheduler",
                address,
                *certificates["client"].options(),
            )
        )
        assert executed() - before == N_TRAIN  # every training log's statistics, on the worker
    report, _ = _results(tmp_path / "fit")
    assert report["cluster"] == {"scheduler": address, "worker_logs": "ship", "tls": True, "tls_ca_file": "ca.pem"}

    stranger = certificates["stranger"]
    foreign = Certificates(certificates["client"].ca, stranger.cert, stranger.key)  # trusts the cluster; not trusted
    for who, connect in (
        ("no certificate", lambda: Client(address, set_as_default=False, timeout=5)),
        ("plain tcp://", lambda: Client(address.replace("tls://", "tcp://"), set_as_default=False, timeout=5)),
        (
            "another CA's certificate",
            lambda: Client(address, security=stranger.security(), set_as_default=False, timeout=5),
        ),
        (
            "a certificate the cluster's CA did not sign",
            lambda: Client(address, security=foreign.security(), set_as_default=False, timeout=5),
        ),
    ):
        started = time.monotonic()
        with pytest.raises((OSError, TimeoutError, TypeError)):
            connect().close()
        assert time.monotonic() - started < REFUSED, who
        # The refused client is half made: collect it here, not when the next Client's start allocates
        # (its __del__ then closes it while that start holds distributed's loop-runner lock: a deadlock).
        gc.collect()
    # Below dask: the scheduler's TLS handshake demands a client certificate of a client that trusts it.
    host, port = address.removeprefix("tls://").rsplit(":", 1)
    context = ssl.create_default_context(cafile=str(certificates["client"].ca))
    context.check_hostname = False
    with (
        pytest.raises(ssl.SSLError, match="CERTIFICATE_REQUIRED|HANDSHAKE_FAILURE"),
        socket.create_connection((host, int(port)), timeout=REFUSED) as raw,
        context.wrap_socket(raw) as tls,
    ):
        tls.recv(1)  # TLS 1.3: the server's refusal arrives after the client's handshake
    # qube-identify with the stranger's certificates: one line, exit 2.
    from qube_koopman.identify.cli.identify import main

    assert main(_argv(cluster_logs, tmp_path / "refused", "--scheduler", address, *stranger.options())) == 2
    assert not (tmp_path / "refused").exists()


@pytest.mark.parametrize("tool", ["cryptography", "openssl"])
def test_certificates_made_either_way_pass_a_mutual_tls_handshake_as_dask_makes_it(tool, tmp_path):
    if tool == "cryptography":
        pytest.importorskip("cryptography")
    elif shutil.which("openssl") is None:
        pytest.skip("no openssl command")
    made = make_certificates(tmp_path / "ca", ["node", "client"], tool)
    server = made["node"].security("scheduler").get_listen_args("scheduler")["ssl_context"]
    client = made["client"].security().get_connection_args("client")["ssl_context"]
    a, b = socket.socketpair()
    with (
        server.wrap_socket(a, server_side=True, do_handshake_on_connect=False) as s,
        client.wrap_socket(b, do_handshake_on_connect=False) as c,
    ):
        s.setblocking(False), c.setblocking(False)
        done = set()
        for _ in range(200):  # the two ends of one handshake, in turn
            for end in (s, c):
                if end not in done:
                    try:
                        end.do_handshake()
                        done.add(end)
                    except (ssl.SSLWantReadError, ssl.SSLWantWriteError):
                        pass
            if len(done) == 2:
                break
        assert len(done) == 2 and s.getpeercert()["subject"] == ((("commonName", "client"),),)


def _run(argv: list[str], capsys) -> tuple[int, str]:
    from qube_koopman.identify.cli.identify import main

    code = main(["--train", "missing-train.mcap", "--test", "missing-test.mcap", "--out", "unused", *argv])
    return code, capsys.readouterr().err


LOGS_MISSING = "qube-identify: error: missing-train.mcap: no such file"  # every cluster check passed


@pytest.mark.parametrize(
    "address",
    [
        "tcp://127.0.0.1:8786",
        "127.0.0.1:8786",
        "tcp://127.1.2.3:8786",
        "tcp://localhost:8786",
        "LOCALHOST:8786",
        "tcp://[::1]:8786",
    ],
)
def test_plain_tcp_on_the_loopback_is_accepted_without_a_warning(address, capsys):
    code, err = _run(["--scheduler", address], capsys)
    assert code == 2 and err.startswith(LOGS_MISSING) and "warning" not in err, err


@pytest.mark.parametrize(
    "address",
    [
        "tcp://10.0.0.5:8786",
        "10.0.0.5:8786",
        "tcp://0.0.0.0:8786",
        "tcp://scheduler.example:8786",
        "ws://[2001:db8::1]:8786",
    ],
)
def test_plain_tcp_off_the_loopback_is_refused_unless_insecure_scheduler(address, capsys):
    code, err = _run(["--scheduler", address], capsys)
    assert code == 2 and len(err.splitlines()) == 1, err
    assert "is neither encrypted nor authenticated: anyone who can reach that port can run any code" in err
    assert "use tls:// with --tls-ca-file, --tls-cert and --tls-key" in err and "--insecure-scheduler" in err
    code, err = _run(["--scheduler", address, "--insecure-scheduler"], capsys)
    warning, error = err.splitlines()
    assert warning.startswith("qube-identify: warning: --insecure-scheduler: ") and "can run any code" in warning
    assert code == 2 and error.startswith(LOGS_MISSING), err


@pytest.fixture(scope="module")
def files(certificates, tmp_path_factory) -> dict[str, str]:
    """The client's files, a file that is no PEM, a folder, a missing path, another CA's key."""
    folder = tmp_path_factory.mktemp("not_certificates")
    (folder / "empty.pem").write_text("")
    client = certificates["client"]
    return {
        "ca": str(client.ca),
        "cert": str(client.cert),
        "key": str(client.key),
        "empty": str(folder / "empty.pem"),
        "folder": str(folder),
        "missing": str(folder / "missing.pem"),
        "other-key": str(certificates["stranger"].key),
    }


TLS = ["--scheduler", "tls://h:8786"]


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--tls-ca-file", "{ca}"], "--tls-ca-file: the certificates of a TLS dask scheduler: give --scheduler tls://"),
        (
            ["--insecure-scheduler"],
            "--insecure-scheduler accepts a plain tcp:// dask scheduler off the loopback: it needs",
        ),
        (
            [*TLS, "--insecure-scheduler"],
            "--insecure-scheduler accepts a plain tcp:// scheduler; --scheduler tls://h:8786",
        ),
        (
            ["--scheduler", "tcp://127.0.0.1:8786", "--tls-ca-file", "{ca}", "--tls-cert", "{cert}"],
            "--tls-ca-file, --tls-cert: certificates secure a tls:// scheduler, "
            "but --scheduler tcp://127.0.0.1:8786 is",
        ),
        (["--scheduler", "10.0.0.5:8786", "--tls-cert", "{cert}"], "is plain tcp: give tls://10.0.0.5:8786"),
        (TLS, "--scheduler tls://h:8786 needs the cluster's CA certificate (--tls-ca-file) and a client certificate"),
        (TLS, "or the same in the dask configuration (distributed.comm.tls.ca-file, distributed.comm.tls.client.cert"),
        (
            [*TLS, "--tls-ca-file", "{ca}"],
            "tls://h:8786 needs a client certificate the cluster's CA signed (--tls-cert",
        ),
        ([*TLS, "--tls-ca-file", "{ca}", "--tls-key", "{key}"], "--tls-key is the private key of --tls-cert: give"),
        (
            [*TLS, "--tls-ca-file", "{missing}", "--tls-cert", "{cert}", "--tls-key", "{key}"],
            "{missing}: no such file (--tls-ca-file: a certificate or key file in PEM)",
        ),
        ([*TLS, "--tls-ca-file", "{ca}", "--tls-cert", "{folder}"], "{folder}: a folder, not a file (--tls-cert"),
        (
            [*TLS, "--tls-ca-file", "{empty}", "--tls-cert", "{cert}", "--tls-key", "{key}"],
            "{empty} (--tls-ca-file): not a CA certificate in PEM",
        ),
        (
            [*TLS, "--tls-ca-file", "{ca}", "--tls-cert", "{cert}"],
            "{cert} (--tls-cert): not a certificate followed by its private key in PEM, and no --tls-key given",
        ),
        (
            [*TLS, "--tls-ca-file", "{ca}", "--tls-cert", "{cert}", "--tls-key", "{other-key}"],
            "{cert} (--tls-cert), {other-key} (--tls-key): not a certificate and its private key in PEM",
        ),
    ],
)
def test_bad_cluster_options_are_one_line_errors_naming_them(argv, message, files, capsys):
    code, err = _run([a.format(**files) for a in argv], capsys)
    assert code == 2 and len(err.splitlines()) == 1, err
    assert err.startswith("qube-identify: error: ") and message.format(**files) in err, err


def _checked(argv: list[str]):
    from qube_koopman.identify.cli.cluster import check_cluster_options
    from qube_koopman.identify.cli.identify import _parser

    args = _parser().parse_args(["--train", "a.mcap", "--test", "b.mcap", *argv])
    check_cluster_options(args, "qube-identify")
    return args


def test_the_certificates_come_from_the_options_or_else_from_the_dask_configuration(certificates, files):
    import dask
    from qube_koopman.core.command import CliError

    client, stranger = certificates["client"], certificates["stranger"]
    assert _checked(["--scheduler", "tcp://127.0.0.1:8786"]).security is None
    security = _checked(["--scheduler", "tls://h:8786", *client.options()]).security
    assert (security.tls_ca_file, security.tls_client_cert, security.tls_client_key) == (
        str(client.ca),
        str(client.cert),
        str(client.key),
    )
    assert security.require_encryption
    configured = {
        "distributed.comm.tls.ca-file": str(stranger.ca),
        "distributed.comm.tls.client.cert": str(stranger.cert),
        "distributed.comm.tls.client.key": str(stranger.key),
    }
    with dask.config.set(configured):
        security = _checked(["--scheduler", "tls://h:8786"]).security
        assert (security.tls_ca_file, security.tls_client_cert, security.tls_client_key) == (
            str(stranger.ca),
            str(stranger.cert),
            str(stranger.key),
        )
        # An option replaces its key; a certificate given comes without the configuration's key (not its own).
        security = _checked(["--scheduler", "tls://h:8786", "--tls-ca-file", files["ca"]]).security
        assert (security.tls_ca_file, security.tls_client_cert) == (str(client.ca), str(stranger.cert))
        with pytest.raises(CliError, match="no --tls-key given"):
            _checked(["--scheduler", "tls://h:8786", "--tls-cert", files["cert"]])
    with (
        dask.config.set({**configured, "distributed.comm.tls.client.key": files["missing"]}),
        pytest.raises(CliError, match="missing.pem: no such file \\(distributed.comm.tls.client.key in the dask"),
    ):
        _checked(["--scheduler", "tls://h:8786"])
