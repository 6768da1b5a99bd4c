"""Agent JIDs that several clients log in with (master.sessions): two live clients are told apart from an
agent that restarted, and said once per episode."""

from master.sessions import MAX_RESOURCES, WINDOW_S, SharedAccounts

JID = "agent-0@farm"


def test_two_clients_whose_messages_interleave_are_said_once():
    shared = SharedAccounts()
    assert shared.seen(JID, "a", 0.0) is None
    assert shared.seen(JID, "a", 2.0) is None
    assert shared.seen(JID, "b", 3.0) is None  # a second resource alone: perhaps a restart
    said = shared.seen(JID, "a", 4.0)  # a speaks again after b began: both are alive
    assert said is not None and "2 clients log in as agent-0@farm (resources a, b)" in said
    assert "give each agent its own JID" in said
    assert shared.seen(JID, "b", 5.0) is None and shared.sharing(JID, 5.0) == ["a", "b"]
    assert shared.sharing("agent-1@farm", 5.0) == []


def test_an_agent_that_restarted_with_a_new_resource_is_not_a_second_client():
    shared = SharedAccounts()
    for t in range(5):
        assert shared.seen(JID, "old", float(t)) is None
    for t in range(6, 12):
        assert shared.seen(JID, "new", float(t)) is None
    assert shared.sharing(JID, 12.0) == []


def test_a_client_silent_for_the_window_no_longer_counts_and_a_new_episode_is_said_again():
    shared = SharedAccounts()
    shared.seen(JID, "a", 0.0)
    shared.seen(JID, "b", 1.0)
    assert shared.seen(JID, "a", 2.0) is not None
    later = 2.0 + WINDOW_S + 1
    assert shared.seen(JID, "b", later) is None and shared.sharing(JID, later) == []  # a went quiet
    shared.seen(JID, "c", later + 1)
    assert shared.seen(JID, "b", later + 2) is not None  # b and c: said again


def test_a_client_that_makes_up_resources_keeps_only_the_most_recent_few_and_a_gone_jid_is_forgotten():
    shared = SharedAccounts()
    for i in range(1000):
        shared.seen(JID, f"r{i}", float(i) / 100)
    assert len(shared.sharing(JID, 10.0)) <= MAX_RESOURCES
    assert shared.sharing(JID, 10.0 + WINDOW_S + 1) == [] and JID not in shared._spans
