"""scripts/profile_server.py's reading of py-spy's native stacks: where each thread waits (a device sync, idle, the
GIL) or runs, from stacks shaped as measured on an H200 (profile_server_reconstruct_16_native_cuda.json)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("profile_server", ROOT / "scripts" / "profile_server.py")
profile_server = importlib.util.module_from_spec(spec)
spec.loader.exec_module(profile_server)


def test_native_waits_tell_a_gil_wait_from_a_sync_an_idle_thread_and_work(tmp_path):
    lines = [
        # a torch call took the GIL back after a CUDA call: a condition wait under it
        "thread (1): isosr-device_0;_batch_sync (isosr_server/engine.py:1);Event.record (torch/cuda/streams.py:1);"
        "THCPEvent_record (libtorch_python.so);pthread_cond_timedwait (libc.so.6);0x7f2ae9698e51 (libc.so.6) 26",
        "thread (1): isosr-device_0;_batch_sync (isosr_server/engine.py:1);synchronize (torch/cuda/__init__.py:1);"
        "THCPModule_cudaSynchronize (libtorch_python.so);pthread_cond_timedwait (libc.so.6) 3",
        "thread (1): isosr-device_0;_worker (concurrent/futures/thread.py:69);PyThread_acquire_lock_timed (python3.12);"
        "0x7f2ae9698e51 (libc.so.6) 35",
        "thread (1): isosr-device_0;_batch_sync (isosr_server/engine.py:1);conv3x3 (isosr_net/fused_kernels.py:1) 36",
        "thread (2): MainThread;Server.run (uvicorn/server.py:85);uv_run (core.c:452);uv__io_poll (linux.c:1);"
        "epoll_pwait (libc.so.6) 50",
    ]
    path = tmp_path / "native.txt"
    path.write_text("\n".join(lines) + "\n")
    threads = profile_server.read_stacks(path)
    device = threads["thread (1): isosr-device_0"]
    assert profile_server.thread_kind(device) == "device"
    assert profile_server.native_waits(device, 100) == {"running": 0.36, "GIL": 0.26, "device sync": 0.03,
                                                         "idle": 0.35}
    assert profile_server.native_waits(threads["thread (2): MainThread"], 100)["idle"] == 0.5
