"""`SessionRouter`: the Ray Serve request router of the replicas (`isosr serve --replicas`), one
class for both kinds of placement (Serve allows one request router per deployment; it runs in
every proxy and deployment handle that routes to the replicas).

- A request with a session id (the ``x-session-id`` header, which Serve's proxy puts in the
  request's ``metadata.session_id``: an upscale session's frames) goes by consistent hashing on
  it, as Serve's ``ConsistentHashRouter`` does: the ring's replica first, then its next replicas
  (``num_fallback_replicas``) when that one does not take it.
- Any other request (a view WebSocket, session-less upscaling, probes, pages) goes to the replica
  with the fewest ongoing requests: all replicas form one rank, in random order, and Serve's
  router takes the one with the lowest queue length that accepts (its cache of each replica's
  ongoing requests, counted up when it sends one and down when that one ends, and re-read from
  the replica, ``RunningReplica.get_queue_len``, when missing or older than
  ``RAY_SERVE_QUEUE_LENGTH_CACHE_TIMEOUT_S``). A view WebSocket is one ongoing request for its
  life, so this is the replica with the fewest active view sessions (besides any HTTP requests
  in flight at that moment); the random order breaks ties. Each proxy counts what it routed
  itself and learns the others' sessions when it re-reads a replica, so with several proxies
  (one per node) the counts may lag by that timeout.

Serve's default power-of-two-choices router looks at two random replicas only: with 2 replicas
it is the same rule, with more it may miss the emptiest one. The replicas' ``record_routing_stats``
(custom stats pushed every ``request_routing_stats_period_s``, 10 s by default) would be staler
than the queue lengths, and Serve's ``LocalityMixin`` (prefer the proxy's own node) would work
against the fewest-sessions rule, so neither is used; requests are routed in arrival order as
``ConsistentHashRouter`` routes them (no ``FIFOMixin``: there are no model ids to match).

Measured on the 2-CPU test machine (view sessions opened one after another and held open, their
count per replica's max - min): 32 over 2 replicas in 10 rounds, Serve's consistent hash on each
request's id (what view sessions got before this router) 2-14, mean 5.8; power-of-two choices 0
in every round; this router 0. 30 over 3 replicas in 5 rounds: power-of-two 0 or 2, this router 0.

The module imports Ray but not the app: the proxies import it by its path (`ROUTER`).
"""

from __future__ import annotations

import random

from ray.serve.experimental.consistent_hash_router import ConsistentHashRouter
from ray.serve.request_router import PendingRequest, RunningReplica

ROUTER = f"{__name__}.SessionRouter"


class SessionRouter(ConsistentHashRouter):
    """Consistent hashing for requests with a session id, the fewest ongoing requests for the rest."""

    async def choose_replicas(self, candidate_replicas: list[RunningReplica],
                              pending_request: PendingRequest | None = None) -> list[list[RunningReplica]]:
        """Ranks of replicas to try in order: the session's ring replicas one by one, or all of
        them as one rank (Serve's router picks the least loaded of a rank)."""
        if pending_request is None or pending_request.metadata.session_id:
            return await super().choose_replicas(candidate_replicas, pending_request)
        pending_request.routing_context.should_backoff = True  # all full: retry with backoff
        return [random.sample(candidate_replicas, len(candidate_replicas))] if candidate_replicas else []
