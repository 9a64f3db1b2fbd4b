#!/usr/bin/env python3
"""scripts/layering.py refuses each kind of forbidden include and passes the allowed ones, on a
small tree made here; then it passes on the checkout itself.

Usage: layering_test.py CHECKOUT
"""
import os
import subprocess
import sys
import tempfile

FILES = {
    # Allowed: an engine on core and extract, the job layer on an engine, the client on io.
    "worker/pu/fit.cc": '#include "worker/core/geometry.h"\n#include "worker/extract/j1a.h"\n',
    "worker/jobs/kind.cc": '#include "worker/pu/pu.h"\n#include <vector>\n',
    "client/main.cc": '#include "worker/io/files.h"\n',
    # Forbidden, one of each kind.
    "worker/io/bad_codec.cc": '#include "worker/core/geometry.h"\n#include "worker/volume/volume_field.h"\n',
    "worker/mls/bad_wire.cc": "#include <grpcpp/grpcpp.h>\n",
    "worker/front/bad_up.h": '#include "worker/jobs/job_kind.h"\n',
    "client/bad_engine.cc": '#include "worker/pu/pu.h"\n',
    "server/bad_render.cc": '#include "worker/render/render.h"\n',
    "server/bad_codec.cc": '#include "worker/io/files.h"\n',
    "bench/bad_bench.cc": '#include "tests/test_shapes.h"\n',
    "worker/jobs/bad_private.cc": '#include "worker/pu/pu_internal.h"\n',
    # Shape rules: a friend, an untyped pointer, another module's internals, a file too long.
    "worker/mls/bad_friend.h": "class A {\n  friend void F();\n};\n",
    "worker/jobs/bad_void.cc": "// shared_ptr<void> in a comment is fine\nstd::shared_ptr<void> held;\n",
    "worker/pu/bad_reach.cc": "void F() { extract::internal::FinishSurface(); }\n",
    "server/bad_long.cc": "int x;\n" * 801,
    "worker/extract/own.cc": "namespace extract::internal {}\n" + "int y;\n" * 790,
    # A job-layer class of 21 member functions is refused; 20, with data members of function
    # type and a nested struct's, pass.
    "worker/jobs/bad_big.h": "class Big {\n public:\n" + "".join(f"  void F{i}(int x);\n" for i in range(21)) + "};\n",
    # Job modules in a cycle (a header and the other's source) are refused at the first module's
    # include; a header included by its own source is no cycle.
    "worker/jobs/loop_a.h": '#include "worker/jobs/loop_b.h"\n',
    "worker/jobs/loop_b.h": "int b;\n",
    "worker/jobs/loop_b.cc": '#include "worker/jobs/loop_b.h"\n#include "worker/jobs/loop_a.h"\n',
    "worker/jobs/fits.h": "class Fits final : public Base {\n public:\n  Fits(int a,\n       int b);\n" +
    "".join(f"  int G{i}() const {{ return {i}; }}\n" for i in range(19)) +
    " private:\n  struct Part {\n    void H();\n  };\n  std::function<void()> done_;\n  std::mutex m_;\n};\n",
}
EXPECTED = {
    "worker/io/bad_codec.cc:2",
    "worker/mls/bad_wire.cc:1",
    "worker/front/bad_up.h:1",
    "client/bad_engine.cc:1",
    "server/bad_render.cc:1",
    "server/bad_codec.cc:1",
    "bench/bad_bench.cc:1",
    "worker/jobs/bad_private.cc:1",
    "worker/mls/bad_friend.h:2",
    "worker/jobs/bad_void.cc:2",
    "worker/pu/bad_reach.cc:1",
    "server/bad_long.cc:801",
    "worker/jobs/bad_big.h:1",
    "worker/jobs/loop_a.h:1",
}


def run(script, root):
    return subprocess.run([sys.executable, script, "--root", root], capture_output=True, text=True)


def main():
    checkout = sys.argv[1]
    script = os.path.join(checkout, "scripts", "layering.py")
    with tempfile.TemporaryDirectory() as root:
        for name, text in FILES.items():
            os.makedirs(os.path.join(root, os.path.dirname(name)), exist_ok=True)
            with open(os.path.join(root, name), "w") as f:
                f.write(text)
        result = run(script, root)
        reported = {line.split(": ")[0] for line in result.stdout.splitlines()}
        if result.returncode != 1 or reported != EXPECTED:
            print(f"expected exit 1 and {sorted(EXPECTED)}, got {result.returncode} and:\n{result.stdout}")
            return 1
    result = run(script, checkout)
    if result.returncode != 0:
        print(f"the checkout breaks its layering:\n{result.stdout}")
        return 1
    print("layering: forbidden includes refused, the checkout passes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
