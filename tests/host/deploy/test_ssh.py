"""host/deploy/ssh.py: remote steps over one shared SSH connection, recorded with
their command; a failing step names itself; copy streams a folder as a tar."""
from __future__ import annotations

import pytest

from host.deploy.options import DeployError, DeployOptions
from host.deploy.ssh import SshSession
from tests.host.deploy.sshd_fixture import SshServer, missing_reason


def test_a_dry_run_records_and_runs_nothing(tmp_path):
    s = SshSession(DeployOptions(target="pi@leg1:2222"), dry_run=True, log=lambda m: None)
    s.open_connection()
    step = s.remote("touch", f"touch {tmp_path / 'x'}\n")
    assert "rc" not in step and not (tmp_path / "x").exists()
    assert s.steps == [step] and step["where"] == "remote"
    argv = s.ssh_argv("true")
    assert argv[argv.index("-p") + 1] == "2222" and "pi@leg1" in argv


@pytest.mark.skipif(missing_reason() is not None, reason=str(missing_reason()))
def test_steps_run_over_one_connection_and_a_failure_names_its_step(tmp_path):
    with SshServer(tmp_path) as srv:
        lines = []
        s = SshSession(DeployOptions(target=f"{srv.target}:{srv.port}", identity=srv.identity,
                                     ssh_options=list(srv.ssh_options)), log=lines.append)
        s.open_connection()
        try:
            assert s.remote("hello", "echo hi\n")["stdout"] == "hi\n"
            src = tmp_path / "src"
            (src / "sub").mkdir(parents=True)
            (src / "sub" / "f.txt").write_text("payload")
            s.copy(src, str(tmp_path / "dest" / "x"))
            assert (tmp_path / "dest" / "x" / "sub" / "f.txt").read_text() == "payload"
            with pytest.raises(DeployError, match=r"step broken failed \(exit 3\): nope"):
                s.remote("broken", "echo nope >&2; exit 3\n")
            assert s.remote("soft", "exit 4\n", check=False)["rc"] == 4
        finally:
            s.close_connection()
        assert [st["step"] for st in s.steps] == ["hello", "copy", "broken", "soft"]
        assert any("[deploy] hello (remote): echo hi" in l for l in lines)
