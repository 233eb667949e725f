#!/usr/bin/python3
"""Asks a gaps service's standard gRPC health service (grpc.health.v1.Health/Check) whether it is SERVING.

The image's HEALTHCHECK, compose's health checks and Kubernetes' exec probes of a service that serves TLS
(the kubelet's own gRPC probes speak plaintext only) run it as gaps-health-check. Exit status 0: SERVING;
1: any other answer, no answer, or a failed call (the reason on stderr).

    gaps-health-check [--address HOST:PORT] [--tls_ca FILE [--tls_server_name NAME]] [--timeout S]

Defaults come from the environment: GAPS_HEALTH_ADDRESS (else 127.0.0.1:50051), GAPS_HEALTH_TLS_CA,
GAPS_HEALTH_TLS_SERVER_NAME. Uses Debian's python3-grpcio; the messages are encoded here (the request of the
whole server's health is empty; the answer holds one enum field), so no generated code is needed.
"""
import argparse
import os
import sys

import grpc

SERVING = 1
STATUS_NAMES = {0: "UNKNOWN", 1: "SERVING", 2: "NOT_SERVING", 3: "SERVICE_UNKNOWN"}


def read_varint(data: bytes, pos: int):
    value, shift = 0, 0
    while True:
        if pos >= len(data):
            raise ValueError("truncated varint")
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, pos
        shift += 7


def health_status(response: bytes) -> int:
    """The status field (1, varint) of a HealthCheckResponse; 0 (UNKNOWN) when absent, as protobuf reads it."""
    status, pos = 0, 0
    while pos < len(response):
        key, pos = read_varint(response, pos)
        field, wire_type = key >> 3, key & 7
        if wire_type == 0:
            value, pos = read_varint(response, pos)
            if field == 1:
                status = value
        elif wire_type == 2:
            length, pos = read_varint(response, pos)
            pos += length
        elif wire_type == 1:
            pos += 8
        elif wire_type == 5:
            pos += 4
        else:
            raise ValueError(f"unexpected wire type {wire_type}")
    if pos != len(response):
        raise ValueError("truncated field")
    return status


def make_channel(args):
    if not args.tls_ca:
        return grpc.insecure_channel(args.address)
    with open(args.tls_ca, "rb") as f:
        credentials = grpc.ssl_channel_credentials(root_certificates=f.read())
    options = [("grpc.ssl_target_name_override", args.tls_server_name)] if args.tls_server_name else []
    return grpc.secure_channel(args.address, credentials, options=options)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--address", default=os.environ.get("GAPS_HEALTH_ADDRESS", "127.0.0.1:50051"))
    parser.add_argument("--tls_ca", default=os.environ.get("GAPS_HEALTH_TLS_CA", ""))
    parser.add_argument("--tls_server_name", default=os.environ.get("GAPS_HEALTH_TLS_SERVER_NAME", ""))
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds")
    args = parser.parse_args(argv)
    try:
        with make_channel(args) as channel:
            check = channel.unary_unary("/grpc.health.v1.Health/Check", request_serializer=None,
                                        response_deserializer=None)
            status = health_status(check(b"", timeout=args.timeout))
    except grpc.RpcError as e:
        print(f"gaps-health-check: {args.address}: {e.code().name}: {e.details()}", file=sys.stderr)
        return 1
    except (OSError, ValueError) as e:
        print(f"gaps-health-check: {args.address}: {e}", file=sys.stderr)
        return 1
    name = STATUS_NAMES.get(status, str(status))
    print(f"gaps-health-check: {args.address}: {name}")
    return 0 if status == SERVING else 1


if __name__ == "__main__":
    sys.exit(main())
