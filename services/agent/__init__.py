"""The robot agent: scans -> mixtures -> Zenoh, with a durable outbox until the server acknowledges."""
