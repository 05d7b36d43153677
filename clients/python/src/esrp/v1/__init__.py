"""The generated esrp.v1 protobuf messages (`esrp_pb2`) and gRPC stubs (`esrp_pb2_grpc`).

Generated from proto/esrp/v1/esrp.proto by tools/generate_proto.py and checked in; never edit them
by hand. Use them for what the typed API does not cover, e.g. with `Client.raw`.
"""
