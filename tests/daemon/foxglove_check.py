"""Every message of an MCAP file against its channel's schema (the tests' stand-in for `mcap doctor`).

protobuf channels: decoded with the schema stored in the file (mcap's protobuf decoder builds the classes
from its FileDescriptorSet), then with Foxglove's official class of that name; the two must agree field for
field. json channels: the payload against the stored JSON Schema (jsonschema). Returns messages per schema.
"""

from __future__ import annotations

import importlib
import json
from collections import Counter
from pathlib import Path

import jsonschema
from google.protobuf.message import Message as ProtobufMessage
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory


def official_class(schema_name: str) -> type[ProtobufMessage]:
    """foxglove.X -> foxglove_schemas_protobuf.X_pb2.X."""
    package, name = schema_name.split(".")
    assert package == "foxglove", schema_name
    cls: type[ProtobufMessage] = getattr(
        importlib.import_module(f"foxglove_schemas_protobuf.{name}_pb2"), name
    )
    return cls


def check_recording(path: Path) -> Counter[str]:
    counts: Counter[str] = Counter()
    factory = DecoderFactory()
    validators: dict[int, jsonschema.protocols.Validator] = {}
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        for schema, channel, message in reader.iter_messages():
            assert schema is not None, channel.topic
            if channel.message_encoding == "protobuf":
                assert schema.encoding == "protobuf"
                decoder = factory.decoder_for(channel.message_encoding, schema)
                assert decoder is not None
                from_file = decoder(message.data)
                official = official_class(schema.name).FromString(message.data)
                # Re-parsed with the official class, the file's decoding is the same message.
                assert official == official_class(schema.name).FromString(from_file.SerializeToString())
                assert official.ListFields(), f"{channel.topic}: empty {schema.name}"
            else:
                assert (channel.message_encoding, schema.encoding) == ("json", "jsonschema")
                validator = validators.get(schema.id)
                if validator is None:
                    document = json.loads(schema.data)
                    validator = validators[schema.id] = jsonschema.Draft202012Validator(document)
                validator.validate(json.loads(message.data))
            counts[schema.name] += 1
    return counts
