"""The Zenoh wire protocol between processes: key expressions, message schemas with their zero-copy
encode/decode and validation, session configuration, and liveliness. It depends only on numpy and zenoh, so
both ends of every message agree on one definition and it can be tested without a model or an engine."""
