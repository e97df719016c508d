"""The reliance certificate: `seal` (build, canonical JSON, digests, verify), `signing` (Ed25519), `consistency`
(verify's recomputation), `merge` (shards), `reproduce`, `compare` and `estimate`."""
