"""The dask cluster options of ``qube-identify`` (``--scheduler`` and its TLS certificates).

dask unpickles the tasks it is sent, so whoever reaches a scheduler's port runs code on every
worker. A scheduler is used over TLS (``tls://``, certificates signed by the cluster's own CA:
dask's schedulers and workers then accept only clients holding one), or over plain ``tcp://`` on
this machine's loopback only, unless ``--insecure-scheduler`` says the network is trusted.
"""

from __future__ import annotations

import argparse
import ipaddress
import re
import sys
from pathlib import Path

from qube_koopman.core.command import CliError

#: Address schemes whose connections are encrypted and authenticated with the certificates.
ENCRYPTED = ("tls", "wss")
#: The TLS options (named as dask's own command-line options): each one's ``Security`` field and
#: the dask configuration key it overrides.
TLS_OPTIONS = {
    "--tls-ca-file": ("tls_ca_file", "distributed.comm.tls.ca-file"),
    "--tls-cert": ("tls_client_cert", "distributed.comm.tls.client.cert"),
    "--tls-key": ("tls_client_key", "distributed.comm.tls.client.key"),
}
_ADDRESS = re.compile(r"(?:(?P<scheme>[a-z]+)://)?(?P<host>[\w.-]+|\[[0-9A-Fa-f:.]+\]):(?P<port>\d{1,5})")


def add_cluster_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--scheduler``, its TLS options, ``--insecure-scheduler`` and ``--worker-logs`` to ``parser``.

    Parameters
    ----------
    parser : argparse.ArgumentParser
    """
    from qube_koopman.core.cli import path, positive_number
    from qube_koopman.identify.model_selection.distributed import DEFAULT_WORKER_TIMEOUT

    cluster = parser.add_argument_group("dask cluster (the documentation's page: A dask cluster, docs/cluster.md)")
    cluster.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="compute on the workers of this dask.distributed scheduler (e.g. tls://host:8786 with "
        "--tls-ca-file, --tls-cert and --tls-key): the search's candidates instead of --n-jobs "
        "local processes, and the per-episode statistics of the fit and of --alpha-sweep "
        "(results equal a local run's); the scheduler and the workers need this package at "
        "this version (checked on connecting); a plain tcp:// address is refused off this "
        "machine's loopback (127.0.0.1, ::1, localhost), since anyone who can reach the port "
        'can run code on the workers; needs pip install "qube-koopman[dask]"',
    )
    cluster.add_argument(
        "--tls-ca-file",
        type=path,
        metavar="FILE",
        help="with a tls:// --scheduler: the cluster's CA certificate (PEM), which signed the "
        "scheduler's, the workers' and this client's certificates (default: "
        "distributed.comm.tls.ca-file of the dask configuration)",
    )
    cluster.add_argument(
        "--tls-cert",
        type=path,
        metavar="FILE",
        help="with a tls:// --scheduler: this client's certificate (PEM), signed by that CA "
        "(default: distributed.comm.tls.client.cert of the dask configuration)",
    )
    cluster.add_argument(
        "--tls-key",
        type=path,
        metavar="FILE",
        help="the private key of --tls-cert (PEM; leave it out when the certificate file holds "
        "it); without --tls-cert, distributed.comm.tls.client.key of the dask configuration",
    )
    cluster.add_argument(
        "--insecure-scheduler",
        action="store_true",
        help="accept a plain tcp:// --scheduler off the loopback, on a private network where "
        "everyone who can reach the scheduler's and the workers' ports is trusted to run "
        "code on them (a warning is printed)",
    )
    cluster.add_argument(
        "--worker-timeout",
        type=positive_number,
        default=DEFAULT_WORKER_TIMEOUT,
        metavar="S",
        help="with --scheduler: give up, exit status 1, when the cluster has had no worker for this "
        "long while results are awaited (every worker stopped, none came back; default "
        f"{DEFAULT_WORKER_TIMEOUT:g})",
    )
    cluster.add_argument(
        "--worker-logs",
        choices=["ship", "shared"],
        help="how the workers get the training logs for the statistics: ship (the default) sends "
        "each log's bytes with its task, for workers that cannot see this machine's files; "
        "shared: each worker reads the log itself at its absolute path here (a shared "
        "file system; checked on every worker before the fit). The search's candidates "
        "always carry the loaded episodes",
    )


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a name, an IPv4 address or a bracketed IPv6 one) is this machine's loopback.

    Only ``localhost`` and the loopback addresses count (127.0.0.0/8, ::1): no name is resolved.

    Examples
    --------
    >>> [is_loopback(h) for h in ("127.0.0.1", "127.4.5.6", "[::1]", "localhost", "10.0.0.5", "myhost")]
    [True, True, True, True, False, False]
    """
    if host.lower() == "localhost":
        return True
    try:
        address = ipaddress.ip_address(host.strip("[]"))
    except ValueError:
        return False
    mapped = getattr(address, "ipv4_mapped", None)  # ::ffff:127.0.0.1
    return address.is_loopback or bool(mapped and mapped.is_loopback)


def check_cluster_options(args: argparse.Namespace, prog: str) -> None:
    """Refuse cluster options that do not fit together, before any work; set ``args.security``.

    ``args.security`` becomes the ``distributed.security.Security`` of a TLS scheduler (the
    options given, the rest from the dask configuration, encryption required), else None. A
    plain (not TLS) scheduler off the loopback is refused unless ``--insecure-scheduler``, which
    prints a warning on stderr.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options of :func:`add_cluster_options`.
    prog : str
        The command's name, for the warning.

    Raises
    ------
    CliError
        A malformed address; TLS options or ``--insecure-scheduler`` without a scheduler they
        apply to; a plain scheduler off the loopback; a TLS scheduler without a CA or a client
        certificate (options or configuration), or with one that is missing or does not load.
    """
    args.security = None
    given = [option for option in TLS_OPTIONS if _option(args, option) is not None]
    if args.scheduler is None:
        if given:
            raise CliError(
                f"{', '.join(given)}: the certificates of a TLS dask scheduler: give --scheduler tls://HOST:PORT"
            )
        if args.insecure_scheduler:
            raise CliError(
                "--insecure-scheduler accepts a plain tcp:// dask scheduler off the loopback: it needs --scheduler"
            )
        return
    found = _ADDRESS.fullmatch(args.scheduler)
    if found is None or not 0 < int(found["port"]) < 65536:
        raise CliError(
            f"--scheduler takes a dask scheduler's address, for example tls://host:8786, got {args.scheduler!r}"
        )
    scheme = found["scheme"] or "tcp"  # dask's default
    where = f"{found['host']}:{found['port']}"
    if scheme in ENCRYPTED:
        if args.insecure_scheduler:
            raise CliError(
                f"--insecure-scheduler accepts a plain tcp:// scheduler; --scheduler {args.scheduler} is "
                "encrypted: leave it out"
            )
        args.security = _security(args)
    elif given:
        raise CliError(
            f"{', '.join(given)}: certificates secure a tls:// scheduler, but --scheduler "
            f"{args.scheduler} is plain {scheme}: give tls://{where} (a scheduler started with the "
            "cluster's certificates)"
        )
    elif not is_loopback(found["host"].strip("[]")):
        risk = (
            f"{scheme}://{where} is neither encrypted nor authenticated: anyone who can reach that port "
            "can run any code on the scheduler and the workers (dask unpickles the tasks)"
        )
        if not args.insecure_scheduler:
            raise CliError(
                f"--scheduler {risk}; use tls:// with --tls-ca-file, --tls-cert and --tls-key (the documentation's "
                "page: A dask cluster, docs/cluster.md), or --insecure-scheduler on a trusted private network"
            )
        print(f"{prog}: warning: --insecure-scheduler: {risk}", file=sys.stderr)


def _security(args: argparse.Namespace):
    """The ``Security`` of a TLS client: the options given, the rest from the dask configuration."""
    try:
        import dask
        from distributed.security import Security
    except ImportError:
        raise CliError(
            '--scheduler needs dask.distributed, which is optional: pip install "qube-koopman[dask]"', status=1
        ) from None
    if args.tls_key is not None and args.tls_cert is None:
        raise CliError("--tls-key is the private key of --tls-cert: give --tls-cert too")
    chosen = {}  # each file (or PEM text) and where it was given: the option, or the configuration key
    for option, (_, key) in TLS_OPTIONS.items():
        value = _option(args, option)
        source = option if value is not None else f"{key} in the dask configuration"
        if value is None and not (option == "--tls-key" and args.tls_cert is not None):  # a key is its cert's
            value = dask.config.get(key, None)
        if value:
            chosen[option] = (str(value), source)
    needed = {
        "--tls-ca-file": "the cluster's CA certificate (--tls-ca-file)",
        "--tls-cert": "a client certificate the cluster's CA signed (--tls-cert and --tls-key)",
    }
    missing = [what for option, what in needed.items() if option not in chosen]
    if missing:
        raise CliError(
            f"--scheduler {args.scheduler} needs {' and '.join(missing)}, or the same in the dask "
            "configuration (distributed.comm.tls.ca-file, distributed.comm.tls.client.cert and .key)"
        )
    for value, source in chosen.values():
        if "\n" not in value and not Path(value).is_file():  # dask also takes the PEM text itself
            what = "a folder, not a file" if Path(value).is_dir() else "no such file"
            raise CliError(f"{value}: {what} ({source}: a certificate or key file in PEM)")
    # Every field read above: one left out would be read from the configuration again.
    fields = {field: chosen.get(option, (None, ""))[0] for option, (field, _) in TLS_OPTIONS.items()}
    security = Security(require_encryption=True, **fields)
    _check_loads(security, chosen)
    return security


def _option(args: argparse.Namespace, option: str):
    """The value of ``option`` (``--tls-cert``: ``args.tls_cert``)."""
    return getattr(args, option.lstrip("-").replace("-", "_"))


def _check_loads(security, chosen: dict[str, tuple[str, str]]) -> None:
    """The certificates load as dask will load them on connecting; else an error naming the files."""
    import ssl

    ca, _ = chosen["--tls-ca-file"]
    try:
        if "\n" in ca:
            ssl.create_default_context(cadata=ca)
        else:
            ssl.create_default_context(cafile=ca)
    except (ssl.SSLError, OSError) as exc:
        raise CliError(f"{_name(*chosen['--tls-ca-file'])}: not a CA certificate in PEM ({exc})") from None
    try:
        security.get_connection_args("client")  # the client's TLS context: its certificate and key
    except (ssl.SSLError, OSError, ValueError) as exc:
        if "--tls-key" not in chosen:
            raise CliError(
                f"{_name(*chosen['--tls-cert'])}: not a certificate followed by its private key in "
                f"PEM, and no --tls-key given ({exc})"
            ) from None
        files = ", ".join(_name(*chosen[o]) for o in ("--tls-cert", "--tls-key"))
        raise CliError(f"{files}: not a certificate and its private key in PEM ({exc})") from None


def _name(value: str, source: str) -> str:
    """A file as an error names it: its path and where it was given (PEM text: only where)."""
    return source if "\n" in value else f"{value} ({source})"


def cluster_report(args: argparse.Namespace) -> dict:
    """report.json's ``cluster``: the scheduler, how the logs travelled, and whether the connection was TLS.

    Parameters
    ----------
    args : argparse.Namespace
        Options checked by :func:`check_cluster_options`.

    Returns
    -------
    dict
        ``scheduler``, ``worker_logs``, ``tls`` (bool) and ``tls_ca_file``: the CA certificate's
        file name (None without TLS, or when the dask configuration holds the certificate itself).
    """
    security = args.security
    ca = getattr(security, "tls_ca_file", None)
    return {
        "scheduler": args.scheduler,
        "worker_logs": args.worker_logs or "ship",
        "tls": security is not None,
        "tls_ca_file": Path(ca).name if ca and "\n" not in ca else None,
    }
