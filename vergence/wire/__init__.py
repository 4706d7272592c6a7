"""What travels between the processes (issue #34: one room for the wire): `keys`, every Zenoh key expression,
built and parsed once; `messages`, every message (msgspec Structs, msgpack maps, schema version `v`); `status`,
the JSON status and workers report, decoded once into typed structs. A message is a claim: each decoder checks
it. No Zenoh here: the services put and take the bytes."""
