"""jobs: claim-order index, run_seconds (time limit over attempts); calibration_plots (plots drawn by the worker)

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-22 06:00:00
"""
from alembic import op
import sqlalchemy as sa


revision = '0002'
down_revision = '0001'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.add_column(sa.Column('run_seconds', sa.Float(), server_default='0', nullable=False))
        # the claim reads queued jobs in (created_at, id) order and filters available_at from the index itself:
        # a claim stays one index probe with 100k jobs queued instead of a scan and a sort
        batch_op.create_index('ix_jobs_claim', ['status', 'created_at', 'id', 'available_at'], unique=False)

    op.create_table('calibration_plots',
    sa.Column('calibration_id', sa.String(length=36), nullable=False),
    sa.Column('name', sa.String(length=64), nullable=False),
    sa.Column('png', sa.LargeBinary(), nullable=False),
    sa.Column('created_at', sa.Float(), nullable=False),
    sa.ForeignKeyConstraint(['calibration_id'], ['calibrations.id'],
                            name=op.f('fk_calibration_plots_calibration_id_calibrations')),
    sa.PrimaryKeyConstraint('calibration_id', 'name', name=op.f('pk_calibration_plots'))
    )


def downgrade() -> None:
    op.drop_table('calibration_plots')
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.drop_index('ix_jobs_claim')
        batch_op.drop_column('run_seconds')
