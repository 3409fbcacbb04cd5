"""Every command sets OpenMP's passive wait policy before torch can load OpenMP, unless the user chose one."""

import os
import subprocess
import sys

import pytest

PROBE = ("import sys, os; import davis_rig.cli.{module}; "
         "print(os.environ.get('OMP_WAIT_POLICY'), 'torch' in sys.modules)")


@pytest.mark.parametrize("module", ["attack", "train", "eval", "record"])
def test_commands_wait_passively_before_torch_loads(module):
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", PROBE.format(module=module)], env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    assert out == ["PASSIVE", "False"]


def test_a_policy_the_user_set_is_kept():
    env = dict(os.environ, OMP_WAIT_POLICY="ACTIVE")
    out = subprocess.run([sys.executable, "-c", PROBE.format(module="attack")], env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    assert out == ["ACTIVE", "False"]
