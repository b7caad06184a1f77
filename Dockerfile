# One image for the API and the workers: `kneemesh serve` or `kneemesh worker`.
FROM python:3.11-slim
RUN apt-get update && apt-get install -y --no-install-recommends libgl1 libxrender1 libglib2.0-0 calculix-ccx \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /app
COPY pyproject.toml README.md ./
COPY kneemesh_core ./kneemesh_core
COPY kneemesh ./kneemesh
COPY services ./services
RUN pip install --no-cache-dir .
# The service never needs root.
RUN useradd --create-home kneemesh && mkdir /data && chown kneemesh /data
USER kneemesh
ENV KNEEMESH_DATA_DIR=/data PYTHONUNBUFFERED=1
EXPOSE 8000
CMD ["kneemesh", "serve", "--host", "0.0.0.0", "--port", "8000"]
