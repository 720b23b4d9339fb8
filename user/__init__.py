"""USER: real-world online policy learning, cloud-edge over gRPC."""

__version__ = "0.1.0"
