# posefuse server image: `docker build -t posefuse .` then `docker run -p 8080:8080 posefuse`.
# The builder uses the same set-up script as CI (scripts/setup.sh) to obtain ONNX Runtime's shared
# library from the pinned Python wheel, so the server and the trainer's checks use one version.

FROM rust:1.92-bookworm AS builder
RUN apt-get update \
    && apt-get install -y --no-install-recommends python3 python3-venv python3-pip \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /src
# Only PyPI is used (the set-up installs the trainer too; the runtime stage keeps just the library).
ENV PIP_NO_CACHE_DIR=1
COPY scripts scripts
COPY models-export models-export
RUN bash scripts/setup.sh
COPY Cargo.toml Cargo.lock build.rs rustfmt.toml ./
COPY proto proto
COPY benches benches
COPY src src
RUN --mount=type=cache,target=/usr/local/cargo/registry \
    --mount=type=cache,target=/src/target \
    cargo build --release --locked --bin posefuse \
    && cp target/release/posefuse /usr/local/bin/posefuse

FROM debian:bookworm-slim
RUN apt-get update \
    && apt-get install -y --no-install-recommends ca-certificates curl \
    && rm -rf /var/lib/apt/lists/* \
    && useradd --system --uid 10001 --home-dir /app --shell /usr/sbin/nologin posefuse
WORKDIR /app
COPY --from=builder /usr/local/bin/posefuse /usr/local/bin/posefuse
COPY --from=builder /src/.ort/lib /app/.ort/lib
COPY models/default /app/models/default
ENV ORT_DYLIB_PATH=/app/.ort/lib/libonnxruntime.so \
    POSEFUSE_MODEL_DIR=/app/models/default \
    POSEFUSE_ADDR=0.0.0.0:8080 \
    RUST_LOG=info,ort=warn
USER posefuse
EXPOSE 8080
HEALTHCHECK --interval=15s --timeout=3s --start-period=30s --retries=3 \
    CMD curl -fsS http://127.0.0.1:8080/healthz || exit 1
ENTRYPOINT ["posefuse"]
CMD ["serve"]
