"""occvo services: inference, registration and map workers on Zenoh, their client and CLI commands."""
