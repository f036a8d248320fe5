"""A SINUMERIK-like OPC UA server for compgate's OPC UA target tests (asyncua).

It holds the three temperature-compensation setting data per axis as Double variables
under the node ids a SINUMERIK OPC UA server is expected to use,
    ns=<SinumerikVarProvider>;s=/NC/_N_AX_SEA_ACX/$SA_TEMP_COMP_ABS_VALUE[u<axis>]
    ...$SA_TEMP_COMP_SLOPE[u<axis>], ...$SA_TEMP_COMP_REF_POSITION[u<axis>]
with the SinumerikVarProvider namespace registered behind decoy namespaces, so a client
that assumes index 2 writes nowhere.

Security None by default; with --secure DIR only Basic256Sha256 SignAndEncrypt, with a
self-signed server certificate made in DIR (any client certificate is accepted).

Users (user name / password):
  writer / writer-pw   holds "SeaWrite": may write the setting data
  reader / reader-pw   may read only: writes answer BadUserAccessDenied
  anonymous            like reader
UserAccessLevel of the setting data is answered per session, as on the control.

Prints "ENDPOINT <url>" and "NS <index>" on stdout once listening, then reads commands
on stdin, one a line, and answers each with one line:
  dump             VALUES {"<node id>": "<16 hex digits of the f64 bits>", ...}
  delay <seconds>  OK   (every later Write answer is delayed that long)
  expire           OK <n>  (closes every client session, as a session timeout would)
  quit             BYE  (then exits; end of stdin exits too)

Test hooks: --write-delay-s (late Write answers), --session-delay-s (slow
CreateSession), --min-session-timeout-s, --lossy (written values kept rounded to
float32, so a read-back differs).
"""

import argparse
import asyncio
import ipaddress
import json
import logging
import struct
import sys
from pathlib import Path

from asyncua import Server, ua
from asyncua.common.callback import CallbackType
from asyncua.crypto import cert_gen
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.server.internal_session import InternalSession
from asyncua.server.user_managers import UserManager

SETTING_DATA = ("$SA_TEMP_COMP_ABS_VALUE", "$SA_TEMP_COMP_SLOPE", "$SA_TEMP_COMP_REF_POSITION")
USERS = {"writer": ("writer-pw", True), "reader": ("reader-pw", False)}


class Users(UserManager):
    """Writers get the Admin role (asyncua's write right), everyone else User."""

    def get_user(self, iserver, username=None, password=None, certificate=None):
        if username is None:
            return User(role=UserRole.User)
        entry = USERS.get(username)
        if entry is None or entry[0] != password:
            return None  # BadUserAccessDenied at ActivateSession
        return User(role=UserRole.Admin if entry[1] else UserRole.User, name=username)


def bits(value: float) -> str:
    return struct.pack(">d", value).hex()


def make_certificate(key_file: Path, cert_file: Path, app_uri: str, usage) -> None:
    """A self-signed application certificate for 127.0.0.1 (key PEM, certificate DER)."""
    key = cert_gen.generate_private_key()
    names = [
        x509.UniformResourceIdentifier(app_uri),
        x509.DNSName("127.0.0.1"),
        x509.DNSName("localhost"),
        x509.IPAddress(ipaddress.ip_address("127.0.0.1")),
    ]
    cert = cert_gen.generate_self_signed_app_certificate(key, app_uri, {}, names, [usage])
    key_file.parent.mkdir(parents=True, exist_ok=True)
    cert_file.parent.mkdir(parents=True, exist_ok=True)
    key_file.write_bytes(cert_gen.dump_private_key_as_pem(key))
    cert_file.write_bytes(cert.public_bytes(Encoding.DER))


async def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--port", type=int, default=0, help="TCP port on 127.0.0.1 (0: any free one)")
    ap.add_argument("--axes", type=int, default=3, help="axes 1..=N")
    ap.add_argument("--namespace-uri", default="SinumerikVarProvider")
    ap.add_argument("--decoys", type=int, default=2, help="namespaces registered before it")
    ap.add_argument("--write-delay-s", type=float, default=0.0, help="delay of every Write answer")
    ap.add_argument("--min-session-timeout-s", type=float, default=5.0, help="shortest session timeout granted")
    ap.add_argument("--secure", metavar="DIR", help="Basic256Sha256 SignAndEncrypt only; server key in DIR")
    ap.add_argument(
        "--make-client-cert",
        metavar="PKI_DIR",
        help="write a client certificate for urn:compgate into PKI_DIR (own/, private/) and exit",
    )
    ap.add_argument("--session-delay-s", type=float, default=0.0, help="delay of every CreateSession answer")
    ap.add_argument("--lossy", action="store_true", help="keep written values as float32 (a REAL store)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR, stream=sys.stderr)
    if args.make_client_cert:
        pki = Path(args.make_client_cert)
        make_certificate(
            pki / "private/private.pem", pki / "own/cert.der", "urn:compgate", ExtendedKeyUsageOID.CLIENT_AUTH
        )
        print("OK", flush=True)
        return

    if args.session_delay_s > 0:
        create_session = InternalSession.create_session

        async def slow_create_session(self, *a, **kw):
            await asyncio.sleep(args.session_delay_s)
            return await create_session(self, *a, **kw)

        InternalSession.create_session = slow_create_session

    server = Server(user_manager=Users())
    await server.init()
    server.iserver.min_session_timeout_ms = args.min_session_timeout_s * 1000
    server.set_endpoint(f"opc.tcp://127.0.0.1:{args.port}/")
    server.set_server_name("compgate test SINUMERIK")
    if args.secure:
        app_uri = "urn:compgate:test:sinumerik"
        await server.set_application_uri(app_uri)
        key_file, cert_file = Path(args.secure) / "server-key.pem", Path(args.secure) / "server-cert.der"
        make_certificate(key_file, cert_file, app_uri, ExtendedKeyUsageOID.SERVER_AUTH)
        await server.load_certificate(str(cert_file))
        await server.load_private_key(str(key_file))
        server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])
    else:
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
    server.set_identity_tokens([ua.AnonymousIdentityToken, ua.UserNameIdentityToken])
    for i in range(args.decoys):
        await server.register_namespace(f"urn:compgate:test:decoy{i}")
    ns = await server.register_namespace(args.namespace_uri)

    sea = await server.nodes.objects.add_folder(ua.NodeId("/NC/_N_AX_SEA_ACX", ns), "SEA")
    nodes = {}
    for axis in range(1, args.axes + 1):
        for name in SETTING_DATA:
            nid = ua.NodeId(f"/NC/_N_AX_SEA_ACX/{name}[u{axis}]", ns)
            var = await sea.add_variable(nid, f"{name}[u{axis}]", ua.Variant(0.0, ua.VariantType.Double))
            # AccessLevel allows writing; the stored UserAccessLevel does not, so only
            # Admin-role sessions (SeaWrite) pass asyncua's write check.
            await var.set_attr_bit(ua.AttributeIds.AccessLevel, ua.AccessLevel.CurrentWrite)
            await var.unset_attr_bit(ua.AttributeIds.UserAccessLevel, ua.AccessLevel.CurrentWrite)
            nodes[nid] = var

    state = {"delay": args.write_delay_s}

    async def before_write(event, _dispatcher):
        if args.lossy:
            # A store that keeps REAL (float32): what is read back is not what was written.
            for wv in event.request_params.NodesToWrite:
                v = wv.Value.Value
                if wv.NodeId in nodes and v is not None and v.VariantType == ua.VariantType.Double:
                    real = struct.unpack(">f", struct.pack(">f", v.Value))[0]
                    wv.Value = ua.DataValue(ua.Variant(real, ua.VariantType.Double))
        if state["delay"] > 0:
            await asyncio.sleep(state["delay"])

    def user_access_level(event, _dispatcher):
        # The control answers UserAccessLevel per user; asyncua stores one per node.
        # The results are the stored DataValues themselves: each is replaced in the
        # answer, never changed, or a writer's read would let readers write.
        may_write = event.user is not None and event.user.role == UserRole.Admin
        results = event.response_params
        for i, rv in enumerate(event.request_params.NodesToRead):
            if rv.AttributeId == ua.AttributeIds.UserAccessLevel and rv.NodeId in nodes:
                level = ua.AccessLevel.CurrentRead.mask
                if may_write:
                    level |= ua.AccessLevel.CurrentWrite.mask
                results[i] = ua.DataValue(ua.Variant(level, ua.VariantType.Byte))

    server.subscribe_server_callback(CallbackType.PreWrite, before_write)
    server.subscribe_server_callback(CallbackType.PostRead, user_access_level)

    async with server:
        port = server.bserver.port
        print(f"ENDPOINT opc.tcp://127.0.0.1:{port}/", flush=True)
        print(f"NS {ns}", flush=True)
        loop = asyncio.get_running_loop()
        while True:
            line = await loop.run_in_executor(None, sys.stdin.readline)
            if not line:
                break
            cmd = line.split()
            if not cmd:
                continue
            if cmd[0] == "dump":
                values = {nid.to_string(): bits(await var.read_value()) for nid, var in nodes.items()}
                print("VALUES " + json.dumps(values), flush=True)
            elif cmd[0] == "delay" and len(cmd) == 2:
                state["delay"] = float(cmd[1])
                print("OK", flush=True)
            elif cmd[0] == "expire":
                sessions = list(server.iserver._external_sessions.values())
                for session in sessions:
                    await session.close_session()
                print(f"OK {len(sessions)}", flush=True)
            elif cmd[0] == "quit":
                print("BYE", flush=True)
                break
            else:
                print(f"ERR unknown command {line.strip()!r}", flush=True)


if __name__ == "__main__":
    asyncio.run(main())
