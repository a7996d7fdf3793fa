"""The network a post-training run builds: the anchor checkpoint's (:func:`anchor_network`).

Kept apart from :mod:`cpalgo.common.recipe_setup` because :mod:`cpalgo.methods` uses it and
that module imports :mod:`cpalgo.methods`.
"""

from __future__ import annotations

import json
import os
import zipfile
from typing import Any, Mapping

__all__ = ["anchor_network"]


def anchor_network(anchor: str | os.PathLike, policy: Any, algo_kwargs: Mapping[str, Any],
                   aliases: Mapping[str, type]) -> tuple[Any, dict[str, Any], str | None]:
    """The network to build for post-training ``anchor``: the checkpoint's policy class and
    ``policy_kwargs``, whatever the recipe says (its weights load into no other network, and
    settings without weights, such as an activation, would otherwise be the recipe's silently).

    Returns ``(policy, algo_kwargs, note)``: ``policy`` is the checkpoint's class, or the name
    in ``aliases`` (the algorithm's ``policy_aliases``) of that class or of its fused subclass
    (``cpalgo.policies``: the same parameters and outputs, faster), so ``MlpLstmPolicy`` stays
    the fused one; ``algo_kwargs`` a copy with the checkpoint's ``policy_kwargs``; ``note`` one
    line naming what of the given ``policy`` / ``policy_kwargs`` differs (None when nothing
    does). A checkpoint without a readable policy class gives the arguments back unchanged.
    """
    from stable_baselines3.common.save_util import json_to_data

    kwargs = dict(algo_kwargs)
    try:
        with zipfile.ZipFile(anchor) as archive:
            data = json.loads(archive.read("data"))
        saved = json_to_data(json.dumps({k: data[k] for k in ("policy_class", "policy_kwargs") if k in data}))
    except (OSError, KeyError, ValueError, zipfile.BadZipFile):
        return policy, kwargs, None
    cls = saved.get("policy_class")
    if not isinstance(cls, type):
        return policy, kwargs, None
    network = dict(saved.get("policy_kwargs") or {})
    chosen: Any = cls
    for name, alias in aliases.items():
        if alias is cls or cls in alias.__bases__:
            chosen = name
            break
    built = aliases[chosen] if isinstance(chosen, str) else chosen
    wanted = aliases.get(policy, policy) if isinstance(policy, str) else policy
    differs = []
    if wanted is not built:
        differs.append(f"policy {getattr(wanted, '__name__', wanted)} (the anchor's: {built.__name__})")
    if kwargs.get("policy_kwargs") is not None and dict(kwargs["policy_kwargs"]) != network:
        differs.append(f"policy_kwargs {dict(kwargs['policy_kwargs'])} (the anchor's: {network})")
    kwargs["policy_kwargs"] = network
    note = None
    if differs:
        note = f"{anchor}: post-training builds the anchor's network, not " + " and ".join(differs)
    return chosen, kwargs, note
