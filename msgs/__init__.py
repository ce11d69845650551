"""The message vocabulary: typed messages, MessagePack codec, zero-copy arrays, JSON Schemas."""
