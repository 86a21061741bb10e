"""The test harness's ROS domains: nodes started by one test session never share one."""

from conftest import fresh_domain_id, isolated_ros_env


def test_any_102_consecutive_domains_are_distinct_and_valid():
    domains = [fresh_domain_id() for _ in range(150)]
    for start in range(len(domains) - 101):
        window = domains[start:start + 102]
        assert len(set(window)) == 102, start
    assert set(domains) == set(range(102))


def test_isolated_env_takes_a_fresh_domain_unless_given_one():
    first, second = isolated_ros_env(), isolated_ros_env()
    assert first["ROS_DOMAIN_ID"] != second["ROS_DOMAIN_ID"]
    assert isolated_ros_env(7)["ROS_DOMAIN_ID"] == "7"
    assert first["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
