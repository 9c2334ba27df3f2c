"""Generated from proto/jitdyn/v1 by scripts/gen_proto.py; do not edit."""
